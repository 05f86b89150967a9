"""Runtime: the machine that wires the planner and the drives together.

Configuration, the cyclic scheduler, the machine state machine, the motion feed, the Modbus TCP
HMI (``runtime.hmi``) and the ``softmotion`` command line.
"""
