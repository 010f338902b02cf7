"""The defense: the relative-motion Kalman filter, the fused detector + filter defense, the safety chains."""
