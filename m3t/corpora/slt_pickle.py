"""slt-style gzip pickles (media kind ``keypoints``), read with the allow-list unpickler (numpy arrays only).

``<name>.{train,dev,test}`` or ``<name>.<split>.pkl.gz``, each a gzip-compressed pickle of a list of
``{name, signer, gloss, text, sign}`` with ``sign`` a (T, D) float array. The originals hold torch tensors; those
are refused (convert to numpy once), never unpickled. What ``sign`` holds is not documented by the format (CNN
features in neccam/slt's Phoenix files, keypoints in some conversions): fit-corpus stores it as it is, never as
joints.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from m3t.corpora.annotation_files import load_data_pickle
from m3t.corpora.base import CorpusAdapter
from m3t.corpora.clip import Clip
from m3t.corpora.listing import Collector, CorpusError, Listing, with_kind
from m3t.corpora.splits import SPLIT_DIRS

SLT_KEYS = ("name", "signer", "gloss", "text", "sign")


@dataclass(frozen=True)
class SltPickleConfig:
    """Options (params.yaml ``corpora.slt_pickle``); ``files`` relative to the root, empty = discover."""

    files: tuple[str, ...] = ()
    fps: float = 25.0
    language: str = "unknown"

    def __post_init__(self) -> None:
        if self.fps <= 0:
            raise ValueError(f"corpora.slt_pickle.fps must be > 0, got {self.fps}")


def split_of_file(path: Path) -> str | None:
    """Split named by ``x.train`` / ``x.dev`` / ``x.test`` / ``x.<split>.pkl.gz`` / ``<split>.pkl.gz``."""
    name = path.name.removesuffix(".pkl.gz")
    return SPLIT_DIRS.get(name.rsplit(".", 1)[-1])


def read_slt_pickle(path: str | Path) -> list:
    """The list of records of one slt-style gzip pickle (numpy arrays allowed, torch tensors refused)."""
    path = Path(path)
    data = load_data_pickle(path, allow_numpy=True, compressed=True)
    if not isinstance(data, list):
        raise CorpusError(f"{path}: expected a list of {{{', '.join(SLT_KEYS)}}} records, found {type(data).__name__}")
    return data


def _slt_problem(entry: object) -> str | None:
    if not isinstance(entry, dict):
        return f"entry is a {type(entry).__name__}, expected a dict with keys {', '.join(SLT_KEYS)}"
    missing = [k for k in SLT_KEYS if k not in entry]
    if missing:
        return f"entry lacks keys {missing}"
    if not isinstance(entry["name"], str) or not entry["name"]:
        return "name is not a non-empty string"
    sign = entry["sign"]
    if not isinstance(sign, np.ndarray) or sign.ndim != 2 or sign.shape[0] == 0 or sign.dtype.kind != "f":
        shape = getattr(sign, "shape", type(sign).__name__)
        return f"sign is {shape}; expected a non-empty (T, D) float array"
    return None


class SltPickleCorpus(CorpusAdapter):
    """Lists the records of slt-style gzip pickles; media = the pickle file, the record index in extra."""

    name = "slt_pickle"
    config_type = SltPickleConfig
    imported_kind = "keypoints"  # fit-corpus imports these clips (m3t.fitting.imports), never tracks them

    def __init__(self, root: str | Path, config: SltPickleConfig | None = None):
        super().__init__(root, config)
        self._lock = threading.Lock()
        self._held: tuple[Path, list] | None = None  # the last file read: every clip of a file is in it

    def entries(self, path: Path) -> list:
        """The records of one file; the last file read is kept (one unpickling per file, not per clip)."""
        with self._lock:
            if self._held is None or self._held[0] != path:
                self._held = (path, read_slt_pickle(path))
            return self._held[1]

    def files(self) -> list[Path]:
        if self.config.files:
            return [self.root / f for f in self.config.files]
        found = sorted(p for p in self.root.glob("*")  # a .pkl.gz without a split is listed, then quarantined
                       if p.is_file() and (split_of_file(p) is not None or p.name.endswith(".pkl.gz")))
        if not found:
            raise CorpusError(f"{self.root} holds no <name>.train/.dev/.test or <name>.<split>.pkl.gz files; "
                              f"point the root at them or set corpora.slt_pickle.files")
        return found

    def listing(self) -> Listing:
        cfg = self.config
        out = Collector(self.root)
        for path in self.files():
            unsafe = out.media_problem(out.rel(path))  # a params value or a symbolic link may lead out of the root
            if unsafe is not None:
                out.quarantine(path, None, None, unsafe)
                continue
            split = split_of_file(path)
            if split is None:
                out.quarantine(path, None, None, "cannot tell the split from the file name (.train/.dev/.test)")
                continue
            for index, entry in enumerate(read_slt_pickle(path)):
                problem = _slt_problem(entry)
                if problem:
                    name = entry.get("name") if isinstance(entry, dict) else None
                    out.quarantine(path, index, name if isinstance(name, str) and name else None, problem)
                    continue
                clip = Clip(id=entry["name"].replace("/", "__"), corpus=self.name, split=split, language=cfg.language,
                            signer=str(entry["signer"]), text=str(entry["text"]), gloss=str(entry["gloss"]),
                            media=out.rel(path), fps=cfg.fps,
                            extra=with_kind("keypoints", index=index, frames=entry["sign"].shape[0],
                                            dims=entry["sign"].shape[1], name=entry["name"]))
                out.add(clip, path, index)
        return out.listing()

    def sequence(self, clip: Clip) -> np.ndarray:
        """The (T, D) float32 ``sign`` array of a listed clip (its whole pickle file is read once and kept)."""
        entries = self.entries(self.root / clip.media)
        index = int(clip.get("index", "-1"))
        if not 0 <= index < len(entries) or _slt_problem(entries[index]) or entries[index]["name"] != clip.get("name"):
            raise CorpusError(f"{self.root / clip.media}: record {index} is no longer clip {clip.id}; "
                              f"list the corpus again")
        return entries[index]["sign"].astype(np.float32)

    def source(self, clip: Clip) -> dict[str, np.ndarray]:
        """``{"sign": (T, D)}`` of a listed clip, for the import."""
        return {"sign": self.sequence(clip)}
