"""Inference you can import: `predict = load(checkpoint)` then `predict(left, right)` on any size.

inputs (what a predictor accepts), padding (pad mode's protocol), programs (the compiled
programs of a process and the twin's split), predictor (Predictor, PredictOptions, load).
"""

from sljax.inference.inputs import prepare_pair, short_repr
from sljax.inference.padding import PadRule, pad_pair, pad_rule
from sljax.inference.predictor import (MODES, PredictOptions, Predictor, load, make_predictor,
                                       model_config)
from sljax.inference.programs import PROGRAMS, forward, twin_split_needed

__all__ = ["MODES", "PROGRAMS", "PadRule", "PredictOptions", "Predictor", "forward", "load",
           "make_predictor", "model_config", "pad_pair", "pad_rule", "prepare_pair",
           "short_repr", "twin_split_needed"]
