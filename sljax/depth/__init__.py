"""What users do next with a model: depth and point clouds (geometry), stereo pairs from files
to files (pairs), stereo video (video)."""
