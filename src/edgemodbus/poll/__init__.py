"""Polling one slave: planner.py turns items into read blocks (pure, no I/O).

Nothing is imported here: ``config`` imports the planner's limits.
"""
