"""sljax.train."""
