"""Where the human demonstrations come from: synthetic catching motions (`synthetic`) or motion
capture read and retargeted onto the robot (`mocap`).
"""
