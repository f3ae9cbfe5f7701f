"""Split names and deterministic hash splits, for corpora that publish no split of their own."""
from __future__ import annotations

import hashlib

SPLITS = ("train", "dev", "test")
SPLIT_DIRS = {"train": "train", "dev": "dev", "val": "dev", "test": "test"}  # a split as folders / files name it


def hash_unit(key: str, salt: str = "") -> float:
    """A deterministic number in [0, 1) from ``key`` (same on every machine and Python run)."""
    digest = hashlib.blake2b(f"{salt}\x00{key}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big") / 2.0 ** 64


def check_fractions(fractions: tuple[float, float, float], option: str) -> None:
    if len(fractions) != 3 or min(fractions) < 0 or abs(sum(fractions) - 1.0) > 1e-6:
        raise ValueError(f"option {option}: expected three non-negative train/dev/test fractions summing to 1, "
                         f"got {fractions}")


def hash_split(key: str, fractions: tuple[float, float, float] = (0.8, 0.1, 0.1), salt: str = "") -> str:
    """Deterministic train / dev / test assignment of ``key`` with the given fractions."""
    u = hash_unit(key, salt)
    if u < fractions[0]:
        return "train"
    return "dev" if u < fractions[0] + fractions[1] else "test"
