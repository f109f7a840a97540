"""Obstacles: range maps -> what guidance and the autopilot consume (sectors, obstacle list).

``detect``: points, ground, OBSTACLE_DISTANCE sectors and connected obstacles of one range map. Pure numpy/scipy.
"""
