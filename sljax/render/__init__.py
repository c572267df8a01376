"""sljax.render: the procedural renderer (scenes, surfaces, sensor, structured light) and the
rendered stereo rig whose unrectified captures test the importers (synth_rig.py). It sits a floor
above sljax.capture: synth_rig writes captures in the importers' layout and calibration."""
