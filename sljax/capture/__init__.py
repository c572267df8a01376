"""sljax.capture: real data into scenes. A stereo rig's calibration and rectification (rig.py,
charuco.py), the Gray-code capture importer (captures.py) and the SCARED keyframe importer."""
