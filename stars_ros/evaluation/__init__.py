"""Offline evaluation: the nested protocol and its folds, fit executors (process pool, Ray),
statistics, and the k-shot design for new people."""
