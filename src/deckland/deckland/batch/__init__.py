"""Batch tools: the in-process runner, campaigns (local pool or Ray), tuning, speed
measurement and the compiled cores."""
