"""Planner: NURBS curves in, per-period setpoints out; pure computation (numpy, no I/O, threads).

Source: Wang, Zhao, Lu, Liu, "Parametric Curve Look-ahead Interpolation Algorithm with Flexible
Acceleration and Deceleration Method", China Mechanical Engineering 23(3), 2012, 299-304.

Name suffixes give units: ``_mm`` distance, ``_s`` time, ``_mm_s`` feed, ``_mm_s2``
acceleration, ``_mm_s3`` jerk; ``u`` is the curve parameter, ``s`` the arc length (mm).
"""
