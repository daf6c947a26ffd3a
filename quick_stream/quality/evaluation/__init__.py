"""Evaluation against ground truth and against other estimators."""
