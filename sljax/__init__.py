"""sljax: stereo disparity networks regularised by structured-light reconstruction."""

__version__ = "0.1.0"
