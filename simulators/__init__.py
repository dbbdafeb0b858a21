"""Simulated backends: each device's simulator serves the same codec as its driver over a real
transport (a pty or a loopback TCP socket) with fault injection; plus the virtual scene and camera.

``simulators`` may import ``drivers`` codecs and ``estimation`` forward models, never ``rig``.
"""
