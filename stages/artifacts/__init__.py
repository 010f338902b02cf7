"""Where outputs live and how the stages read them back (paths, readers, checkpoints, data)."""
