"""Shared pure helpers (frames, parameter specs) and thin rclpy utilities used by every
deckland node.
"""
