"""The old home of the convolution kernels, now `sljax.kernels`: re-exports its public names."""

from sljax.kernels import (BLOCK_VALUES, Conv2D, Conv3D, ConvTranspose3D, PaddingLike, conv2d,
                           conv3d, conv_impl, conv_transpose3d, fold_conv3d, lax_conv3d,
                           phase_conv_transpose3d, resolve_padding, tap_products_conv3d,
                           transpose_padding)

__all__ = ["BLOCK_VALUES", "Conv2D", "Conv3D", "ConvTranspose3D", "PaddingLike", "conv2d", "conv3d",
           "conv_impl", "conv_transpose3d", "fold_conv3d", "lax_conv3d", "phase_conv_transpose3d",
           "resolve_padding", "tap_products_conv3d", "transpose_padding"]
