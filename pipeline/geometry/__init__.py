"""Geometry: rotations (every conversion), the pinhole camera, chaser trajectories."""
