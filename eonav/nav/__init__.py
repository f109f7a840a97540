"""Navigation and the autopilot link: MAVLink in (attitude, position, clock offset), time sync of frames to
navigation, MAVLink out (OBSTACLE_DISTANCE). The only place pymavlink is imported; no zenoh.
"""
