"""Closed-loop rendezvous guidance flown on the pose estimates."""
