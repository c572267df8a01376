"""Training: config and presets, state, the sharded step, the loop, resuming."""
