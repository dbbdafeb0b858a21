"""The files sssrig reads and writes: session folders, provenance and JSON, images, maps, scene files, the calibration
file.
"""
