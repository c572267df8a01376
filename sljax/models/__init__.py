"""Trained models: checkpoints saved and restored (checkpoint), what orbax raises as one line
(failures), and a trained model read back for inference or fine-tuning (load)."""
