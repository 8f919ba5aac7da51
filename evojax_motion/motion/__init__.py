"""Motions as fixed-length arrays: the time grid and its derivatives (`timegrid`), the torque cost
of eq. 5 (`objective`), the database of primitives (`database`), joint-angle branches (`angles`) and
checks against the robot's limits (`feasibility`).
"""
