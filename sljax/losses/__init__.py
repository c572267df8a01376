"""Losses: structured-light reconstruction, disparity, and the multi-task weighting strategies."""

from sljax.losses.disparity import disparity_loss, disparity_mask, masked_disparity_loss, masked_mae
from sljax.losses.sl import sl_bce, sl_grad_l2, sl_loss
from sljax.losses.weighting import (STRATEGIES, constant_weights, dwa_weights, epoch_weights,
                                    init_uncertainty, uncertainty_loss, weighted_loss)
