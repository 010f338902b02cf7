"""File formats: our model checkpoints and render folders, SPEED / SPEED+ labels, cameras and folders, lab recordings."""
