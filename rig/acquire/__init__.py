"""Acquisition: rig geometry and patterns, capture plans, the runner, device factory and simulators, capture and
resume.
"""
