"""Running a trained model outside JAX: ONNX export (jax2onnx, checked by ONNX Runtime)."""
