"""The one metrics function (metrics) and scoring a predictor on a dataset (scoring)."""
