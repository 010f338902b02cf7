"""Evaluation: attack schedules, sequences, robustness rows, the lab domain, intervals, splits."""
