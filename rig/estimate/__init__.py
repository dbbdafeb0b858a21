"""Estimates: of sessions (``sessions``), scene files (``scenes``), capture folders (``capture_folder`` and its parts),
with their Monte Carlo references (``reference``).
"""
