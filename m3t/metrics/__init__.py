"""Metrics used by every model: DTW joint / vertex errors (dtw, procrustes, motion), BLEU-4 / ROUGE-L (text), codebook statistics, vertex errors."""
