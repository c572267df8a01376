"""Structured-light codes, raw-capture decoding and stereo matching of decoded codes."""

from sljax.sl.codes import (CODES, decode, encode, inverse, num_bits, pattern_columns, patterns,
                            patterns_with_inverses)
from sljax.sl.decode import (DecodeConfig, Decoded, column_from_bits, count_patterns,
                             decode_captures, has_inverses)
from sljax.sl.match import disparity_from_codes

__all__ = ["CODES", "decode", "encode", "inverse", "num_bits", "pattern_columns", "patterns",
           "patterns_with_inverses", "DecodeConfig", "Decoded", "column_from_bits",
           "count_patterns", "decode_captures", "has_inverses", "disparity_from_codes"]

# Importing the submodule sljax.sl.decode above rebinds the package attribute `decode` to that
# module; the documented `sljax.sl.decode` (see __all__) is the code function.
from sljax.sl.codes import decode  # noqa: E402,F811
