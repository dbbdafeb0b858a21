"""Monte Carlo references of the estimates: the shared renderer bridge (``mc_reference``), scene files'
(``scene_reference``), capture folders' spheres (``folder_reference``).
"""
