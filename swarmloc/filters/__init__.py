"""The one Kalman core (kalman.py: unscented transform, gated updates, Cholesky helpers) and the fusion steps built on it (fusion.py: EKF update, covariance intersection, naive fusion)."""
