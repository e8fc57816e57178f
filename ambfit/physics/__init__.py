"""The physics: the bearing description, the force model (Eq. 3-4) and unmodelled effects."""
