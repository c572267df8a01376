"""Exact fast kernels for the CPU: convolutions (3D, transposed 3D, 2D), 2x2 max pooling and
the phase-upsampled disparity regression, each with a hand-written gradient; and for a GPU, the
transposed 3D convolution in forms cuDNN runs natively, forward and backward.

Guarantees. Every implementation of a convolution equals `lax.conv_general_dilated` in value
and in both gradients to float rounding, for any strides, padding and blocking; the pooling
equals `nn.max_pool` (gradient to the first maximum, ties included) and the regression the
plain composition of upsampling, softmax and regression. Guarded by tests/test_conv3d.py
(each kernel against lax, every blocking, bfloat16, the modules against flax's),
tests/test_conv_impl.py (whole networks built with "lax" and "fast" in one process: outputs
and parameter gradients in float64), tests/test_conv_transpose_gpu.py (the GPU forms against
lax in float64, their programs' convolution patterns, PSMNet's hourglass with them),
tests/test_reference_psmnet.py (PSMNet with "gpu" against the PyTorch reference's outputs),
tests/test_unet.py::test_max_pool_equals_flax_max_pool and
tests/test_psmnet.py::test_regress_upsampled_equals_the_composition.

Why. XLA:CPU's 3D convolution is slow (tens of GFLOP/s on 2 cores, and its stride-2 and
transposed gradients take seconds at PSMNet's sizes), while its 2D convolution is close to
PyTorch's conv3d; its kernel gradients and select-and-scatter are slow as well. So:
* `fold_conv3d` (fold.py): a 3D conv is a sum over depth taps of 2D convs with depth folded
  into the batch, over blocks of output planes (`block_values`, default `BLOCK_VALUES`; a
  program may give the kernel gradients blocks of their own with `grad_blocks`). Three depth
  taps at depth stride 1 (and so the input gradient of such a layer) run by pairs of output
  planes, Winograd's F(2, 3) in depth: four 2D convs per two planes instead of six.
* `phase_conv_transpose3d` (phase.py): a stride-s transposed conv is s^3 output phases
  sharing one folded conv, so the zeros of the dilated input are never multiplied.
* `conv2d` (conv2d.py): XLA's 2D conv with its kernel gradient summed over row blocks.
* `tap_products_conv3d` (fold.py): stride-1 layers with few outputs as one matmul of taps.
Rejected at PSMNet's 1/4-resolution shapes (B=1, D=24, H=W=64, C=32/64): im2col + one matmul
(the 27-fold patch copy: 3-4x slower than the fold), folding depth and height (1D convs,
slower), concatenating the depth taps on channels (same speed or slower, 3x memory).

Which runs. `impl` = "auto" | "lax" | "fast" | "gpu" | "gpu-phase" (impl.py): "lax" is the
plain `lax.conv_general_dilated`; "gpu" and "gpu-phase" are XLA's convolutions too, except the
stride-s transposed 3D convolution (`gpu_conv_transpose3d`, conv3d.py): its forward as
cuDNN's backward-data convolution ("gpu") or the phases' one stride-1 conv ("gpu-phase"),
its gradients as the adjoint strided conv and that conv's weight gradient, all of which
XLA:GPU hands to cuDNN's native kernels (the lax form's kernel gradient is a conv of the
dilated input that cuDNN runs in a slow fallback). "auto" is "fast" on CPU, "gpu" on a GPU
and "lax" elsewhere; None, i.e. nothing explicit, takes $SLJAX_CONV3D (any of these), else
"auto". The networks carry the choice as their `conv_impl` field, resolved when the model is
constructed (`ResolvesConvImpl`), and pass it to every convolution module, so two models
built with different choices run side by side in one process. The kernel functions and
modules called with impl=None still read the environment when traced (the networks never do
so). The pooling and the regression have one form, used on every platform. Every choice has
the parameters of flax's modules, so checkpoints and converted weights load into any.
"""

from sljax.kernels.args import (PaddingLike, explicit_padding, ntuple, pairs, resolve_padding,
                                transpose_padding)
from sljax.kernels.blocks import BLOCK_VALUES, grad_block_values, grad_blocks
from sljax.kernels.conv2d import conv2d
from sljax.kernels.conv3d import (conv3d, conv_transpose3d, fold_conv3d, gpu_conv_transpose3d,
                                  lax_conv3d, phase_conv_transpose3d)
from sljax.kernels.fold import tap_products_conv3d
from sljax.kernels.impl import ENV_IMPL, IMPLS, XLA_IMPLS, ResolvesConvImpl, auto_impl, conv_impl
from sljax.kernels.modules import Conv2D, Conv3D, ConvBase, ConvTranspose3D
from sljax.kernels.pool import max_pool_2x2
from sljax.kernels.regression import phase_regression
from sljax.kernels.vjp import vjp_saving_inputs

__all__ = ["BLOCK_VALUES", "ENV_IMPL", "IMPLS", "XLA_IMPLS", "Conv2D", "Conv3D", "ConvBase",
           "ConvTranspose3D", "PaddingLike", "ResolvesConvImpl", "auto_impl", "conv2d", "conv3d",
           "conv_impl", "conv_transpose3d", "explicit_padding", "fold_conv3d",
           "gpu_conv_transpose3d", "grad_block_values", "grad_blocks", "lax_conv3d",
           "max_pool_2x2", "ntuple", "pairs", "phase_conv_transpose3d", "phase_regression",
           "resolve_padding", "tap_products_conv3d", "transpose_padding", "vjp_saving_inputs"]
