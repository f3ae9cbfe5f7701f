"""Metrics shared by every model: codebook statistics, vertex errors (and, later, DTW joint errors)."""
