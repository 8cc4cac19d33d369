"""Training and fitting scripts built on torchbrdf (SVBRDF recovery)."""
