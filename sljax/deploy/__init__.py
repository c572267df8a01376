"""Deployable files of a trained model: serialised StableHLO (stablehlo, jax.export) and ONNX
checked by ONNX Runtime (onnx, conv)."""
