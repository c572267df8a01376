"""sljax.sl."""
