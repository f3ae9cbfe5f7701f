"""Metrics used by every model: DTW joint / vertex errors (dtw, procrustes, motion) and the one motion scorer over
body-model parameters (scorer), BLEU-4 / ROUGE-L (text), codebook statistics, vertex errors."""
