"""Self-supervised training of the covariance network (Algorithm 1 of the paper)."""
