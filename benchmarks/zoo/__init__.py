"""Helpers of the scene zoo (benchmarks/scene_zoo.py, issue 15): scene drawing (:mod:`.scenes`), Monte Carlo
frames written as scene-file folders (:mod:`.frames`), and the status contract and acceptance rules
(:mod:`.rules`)."""
