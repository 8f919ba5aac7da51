"""The online half of sec. 3.2: a motion for a new target by interpolation in the learned database,
timed within the robot's limits (`generation`), ball catching (`catching`) and execution in
MuJoCo (`simulate`).
"""
