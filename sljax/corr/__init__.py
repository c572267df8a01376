"""sljax.corr."""
