"""sljax.data."""
