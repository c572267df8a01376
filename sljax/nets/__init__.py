"""sljax.nets."""
