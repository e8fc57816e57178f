"""Estimation: the least-squares core, the paper's closed form, posteriors, information and design."""
