"""The planner process: plans the jobs the cycle asks for into the shared setpoint rings."""
