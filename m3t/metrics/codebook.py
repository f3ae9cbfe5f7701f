"""Codebook statistics of a token set (M3T Tab. 3 utilisation, Tab. A.2 count SD, Fig. A.3 histograms).

Axis legend: K codebook size.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np


def token_counts(indices: Iterable[np.ndarray], codebook_size: int) -> np.ndarray:
    """(K,) int64 number of times each code occurs in the given index arrays."""
    counts = np.zeros(codebook_size, dtype=np.int64)
    for idx in indices:
        idx = np.asarray(idx).reshape(-1)
        if idx.size and (idx.min() < 0 or idx.max() >= codebook_size):
            raise ValueError(f"token index out of range [0, {codebook_size}): [{idx.min()}, {idx.max()}]")
        counts += np.bincount(idx, minlength=codebook_size)
    return counts


def codebook_stats(counts: np.ndarray) -> dict[str, float]:
    """utilisation_pct: % of codes used at least once; count_sd: standard deviation of the per-code counts
    (population SD, as Tab. A.2); perplexity: exp(entropy) of the code distribution; perplexity_per_code:
    perplexity / K (1 = every code equally often); tokens: total; tokens_per_code: tokens / K.

    Utilisation only means something with many more tokens than codes: N tokens spread uniformly over K codes
    leave a share (1 - 1/K)^N unused (at N = K, 37 %), so read it beside ``tokens_per_code`` (at 10, under
    0.005 % of a uniform codebook goes unused) and ``perplexity_per_code``, which does not saturate."""
    total = int(counts.sum())
    probs = counts / max(total, 1)
    nz = probs[probs > 0]
    perplexity = float(np.exp(-(nz * np.log(nz)).sum())) if total else 0.0
    return {
        "utilisation_pct": 100.0 * float((counts > 0).mean()),
        "count_sd": float(counts.std()),
        "perplexity": perplexity,
        "perplexity_per_code": perplexity / len(counts),
        "tokens": float(total),
        "tokens_per_code": total / len(counts),
    }


def plot_token_histogram(counts: np.ndarray, title: str, path: str | Path) -> Path:
    """Bar chart of code frequencies sorted by rank (like M3T Fig. A.3), saved as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    stats = codebook_stats(counts)
    fig, axes = plt.subplots(1, 2, figsize=(9, 2.8))
    axes[0].bar(np.arange(len(counts)), counts, width=1.0, color="tab:blue")
    axes[0].set_xlabel("code index")
    axes[0].set_ylabel("count")
    axes[1].bar(np.arange(len(counts)), np.sort(counts)[::-1], width=1.0, color="tab:orange")
    axes[1].set_xlabel("code rank")
    fig.suptitle(f"{title}: {stats['utilisation_pct']:.1f}% used, count SD {stats['count_sd']:.1f}", fontsize=9)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return path
