"""Disturbance-observer altitude controller (paper eqs. 6, 13-19) and a PID baseline, with
its ROS 2 node.
"""
