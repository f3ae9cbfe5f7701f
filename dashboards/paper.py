"""The papers' own numbers, shown beside the measured tables for reference (never mixed into them).

Copied from the tables of the two papers (M3T: Tab. 1-4; SGSA: Tab. 1-3) as published, on their corpora
(How2Sign, CSL-Daily, Phoenix14T, NMFs-CSL); the platform's tables are measured on whatever corpus the store
holds, by the definitions each table names, so the two are comparable in layout, not in value.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class PaperTable:
    caption: str
    header: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]


_DTW = ("PA body", "PA hand", "JPE body", "JPE hand")
M3T = {
    "M3T Tab. 1": PaperTable(
        "SLP, DTW-PA-JPE / DTW-JPE as published, on How2Sign (H2S), CSL-Daily (CSL), Phoenix14T (Phx)",
        ("method", *(f"{c} {g}" for c in ("H2S", "CSL", "Phx") for g in _DTW)),
        (("Prog. Trans.", "14.15", "11.57", "14.74", "30.17", "15.98", "12.91", "16.30", "32.63", "13.67", "11.95",
          "15.01", "31.77"),
         ("T2S-GPT", "11.48", "6.39", "12.65", "18.44", "11.94", "5.93", "12.32", "15.43", "10.38", "6.47", "11.65",
          "19.09"),
         ("SOKE", "6.82", "2.35", "7.75", "10.08", "6.24", "1.71", "7.38", "9.68", "4.77", "1.38", "6.04", "7.72"),
         ("M3T w/o SLT", "4.52", "2.42", "5.02", "8.94", "4.13", "1.59", "4.77", "9.94", "3.54", "1.54", "4.17",
          "9.14"),
         ("M3T w/ SLT", "4.28", "2.28", "4.86", "9.44", "3.97", "1.51", "4.63", "9.28", "3.41", "1.46", "4.02",
          "8.55"))),
    "M3T Tab. 2": PaperTable(
        "Back-translation, ROUGE-L (R) and BLEU-4 (B4)",
        ("method", "H2S R", "H2S B4", "CSL R", "CSL B4", "Phx R", "Phx B4"),
        (("GT 3DMM", "18.68", "2.04", "27.14", "7.11", "35.83", "11.84"),
         ("M3T w/o SLT", "12.32", "1.58", "17.27", "4.74", "31.14", "10.16"),
         ("M3T w/ SLT", "13.15", "1.72", "20.23", "5.80", "32.12", "10.58"))),
    "M3T Tab. 3": PaperTable(
        "Tokenizer ablation: PA-VPE (mm) and codebook use (%), averaged across datasets",
        ("Q", "BS", "HS", "PA-VPE body", "PA-VPE hand", "PA-VPE face", "util body", "util hand", "util face"),
        (("VQ", "16", "1024", "20.67", "5.61", "1.35", "67.3", "72.5", "78.8"),
         ("FSQ", "16", "1024", "16.11", "4.94", "1.18", "96.4", "98.1", "99.0"),
         ("FSQ", "128", "1024", "24.85", "6.52", "1.55", "84.1", "86.9", "89.3"),
         ("FSQ", "64", "1024", "21.73", "5.98", "1.42", "89.7", "92.4", "94.1"),
         ("FSQ", "32", "1024", "18.92", "5.37", "1.30", "93.2", "95.7", "97.0"),
         ("FSQ", "16", "512", "17.03", "5.12", "1.08", "94.9", "97.2", "99.5"),
         ("FSQ", "16", "2048", "16.84", "4.98", "1.22", "97.1", "98.5", "99.3"))),
    "M3T Tab. 4": PaperTable(
        "Recognition on NMFs-CSL, top-1 / top-5 accuracy (%)",
        ("method", "Overall T-1", "Overall T-5", "Conf. T-1", "Conf. T-5", "Norm. T-1", "Norm. T-5"),
        (("ST-GCN", "59.9", "86.8", "42.2", "79.4", "83.4", "96.7"),
         ("BEST", "68.5", "94.4", "49.0", "90.3", "94.6", "99.7"),
         ("ScalingUp (pre-trained)", "80.2", "97.5", "67.2", "95.7", "97.5", "99.8"),
         ("M3T", "74.1", "95.1", "58.3", "93.0", "93.5", "97.6"))),
}

_BT = ("BLEU-4", "BLEU-3", "BLEU-2", "BLEU-1", "ROUGE")
_SPLIT_HEADER = tuple(f"{split} {m}" for split in ("dev", "test") for m in _BT)
SGSA = {
    "SGSA Tab. 1": PaperTable(
        "Skeletal graph layers L, back-translation on PHOENIX14T", ("L", *_SPLIT_HEADER),
        (("0 (SA)", "14.25", "17.73", "23.47", "34.79", "37.65", "13.64", "17.03", "23.09", "35.03", "36.59"),
         ("1", "14.37", "17.67", "23.13", "33.95", "36.98", "13.63", "17.08", "23.17", "35.39", "37.05"),
         ("2", "14.50", "18.14", "24.10", "35.96", "38.09", "13.85", "17.23", "23.14", "34.93", "37.33"),
         ("3", "14.53", "18.02", "24.00", "35.71", "37.62", "13.72", "17.23", "23.10", "34.45", "36.99"),
         ("4", "14.68", "18.30", "24.31", "36.16", "38.51", "14.05", "17.59", "23.73", "35.63", "37.47"),
         ("5", "14.72", "18.39", "24.29", "35.79", "38.72", "14.27", "17.79", "23.79", "35.72", "37.79"))),
    "SGSA Tab. 2": PaperTable(
        "Temporal adjacency N, back-translation on PHOENIX14T", ("N", *_SPLIT_HEADER),
        (("inf", "14.72", "18.39", "24.29", "35.79", "38.72", "14.27", "17.79", "23.79", "35.72", "37.79"),
         ("1", "15.15", "18.67", "24.47", "35.88", "38.44", "14.33", "17.77", "23.72", "35.26", "37.96"),
         ("2", "15.09", "18.51", "24.43", "36.17", "38.04", "14.07", "17.62", "23.91", "36.28", "37.82"),
         ("3", "15.08", "18.84", "24.89", "36.66", "38.95", "14.32", "17.95", "24.04", "36.10", "38.38"),
         ("5", "14.90", "18.81", "25.30", "37.31", "39.55", "14.21", "17.79", "23.98", "35.88", "38.44"))),
    "SGSA Tab. 3": PaperTable(
        "Baselines on PHOENIX14T, text to pose", ("approach", *_SPLIT_HEADER),
        (("Progressive Transformers", "11.82", "14.80", "19.97", "31.41", "33.18", "10.51", "13.54", "19.04", "31.36",
          "32.46"),
         ("Adversarial Training", "12.65", "15.61", "20.58", "31.84", "33.68", "10.81", "13.72", "18.99", "30.93",
          "32.74"),
         ("Mixture Density Networks", "11.54", "14.48", "19.63", "30.94", "33.40", "11.68", "14.55", "19.70", "31.56",
          "33.19"),
         ("Mixture of Motion Primitives", "14.03", "17.50", "23.49", "35.23", "37.76", "13.30", "16.86", "23.27",
          "35.89", "36.77"),
         ("Skeletal Graph Self-Attention", "15.15", "18.67", "24.47", "35.88", "38.44", "14.33", "17.77", "23.72",
          "35.26", "37.96"))),
}
