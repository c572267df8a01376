"""Disparity from structured-light patterns by correlation, and pattern uncertainty analysis."""

from sljax.corr.correlation import choose_block
from sljax.corr.correlation import cost_volume
from sljax.corr.correlation import default_max_disp
from sljax.corr.correlation import sl_disparity
from sljax.corr.uncertainty import analyse_uncertainty
from sljax.corr.uncertainty import pattern_uncertainty
from sljax.corr.uncertainty import plot_uncertainty_histogram
from sljax.corr.uncertainty import plot_uncertainty_maps
from sljax.corr.uncertainty import view_uncertainty

__all__ = [
    "analyse_uncertainty", "choose_block", "cost_volume", "default_max_disp",
    "pattern_uncertainty", "plot_uncertainty_histogram", "plot_uncertainty_maps",
    "sl_disparity", "view_uncertainty",
]
