"""Apron state estimator: IR beacon pixels to relative position/velocity (eqs. 27-35) and
deck vertical state.
"""
