"""File formats of other tools' data sets (SPEED / SPEED+ labels and cameras)."""
