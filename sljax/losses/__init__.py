"""sljax.losses."""
