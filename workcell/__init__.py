"""The workcell description: what the lab holds and where, read by every other layer.

Scene files (objects, table, cameras, gripper, GelSight geometry, and the effects a
simulation of it calls for, by name) and the kinematics that relate tool, finger and gel
frames. It imports nothing of the project above it, so the lab nodes and the simulated
world read the same description.
"""
