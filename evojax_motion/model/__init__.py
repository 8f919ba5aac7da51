"""The robot: its MJCF model and limits (`robot`), inverse dynamics by RNEA or MJX (`dynamics`,
`rnea`, `mjx`) and inverse kinematics (`ik`).
"""
