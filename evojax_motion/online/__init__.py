"""The online half of sec. 3.2: a motion for a new target by interpolation in the learned database
(`generation`), reachable targets (`reach`), timed within the robot's limits (`limits`; what the
user is told about them: `explain`), ball catching (`catching`) and execution in MuJoCo
(`simulate`). Their settings: `settings.online`.
"""
