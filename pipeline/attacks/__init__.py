"""Attacks on the pose network and the safety chain, and benign corruptions."""
