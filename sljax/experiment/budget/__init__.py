"""The pilots' budget rules: calibration of epochs by the plateau rule, the overfitting regime."""
