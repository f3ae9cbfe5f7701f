"""The written synthetic corpus: ``clips.jsonl`` + ``motion/<id>.npz`` per clip, written atomically
(:func:`write_corpus`) and read back (:class:`SyntheticCorpus`; :class:`SyntheticAdapter` behind
:func:`m3t.corpora.base.open_corpus`).

A motion file holds the ground truth of one clip: ``param__<modality>`` (T, D) float32 per modality of the body
model, ``identity`` (P,) and ``camera`` (the :class:`~m3t.camera.Camera` as JSON).
"""
from __future__ import annotations

import dataclasses
import json
import shutil
import tempfile
import zipfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from m3t.atomic import replace_dir
from m3t.camera import Camera
from m3t.corpora.base import CorpusAdapter
from m3t.corpora.clip import Clip
from m3t.corpora.listing import Listing, with_kind
from m3t.dataclass_io import build_dataclass
from m3t.declared import open_npz


@dataclass(frozen=True)
class SyntheticClip:
    """One generated clip: its record and its ground truth (what one motion file holds)."""

    clip: Clip
    params: dict[str, np.ndarray]  # modality -> (T, D) float32
    identity: np.ndarray  # (P,)
    camera: Camera


def write_corpus(clips: list[SyntheticClip], root: str | Path) -> Path:
    """Write clips.jsonl + motion/<id>.npz into a temp dir, then swap it in (never a half-written corpus)."""
    root = Path(root)
    root.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=root.parent, prefix=f".{root.name}."))
    try:
        (tmp / "motion").mkdir()
        with open(tmp / "clips.jsonl", "w", encoding="utf-8") as fh:
            for c in clips:
                fh.write(json.dumps(asdict(c.clip), ensure_ascii=False) + "\n")
                np.savez(tmp / c.clip.media, identity=c.identity, camera=np.array(json.dumps(c.camera.as_dict())),
                         **{f"param__{k}": v for k, v in c.params.items()})
        replace_dir(tmp, root)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return root


class SyntheticCorpus:
    """Reader of a written synthetic corpus."""

    def __init__(self, root: str | Path):
        self.root = Path(root)

    def clips(self) -> list[Clip]:
        index = self.root / "clips.jsonl"
        if not index.exists():
            raise FileNotFoundError(f"{index} not found; generate the corpus first (dvc repro generate-corpus)")
        out = []
        for n, line in enumerate(index.read_text(encoding="utf-8").splitlines(), 1):
            try:
                d = json.loads(line)
                out.append(build_dataclass(Clip, d, "clip"))
            except (ValueError, TypeError) as exc:
                raise ValueError(f"{index} line {n}: not a clip record ({exc})") from exc
        return out

    def ground_truth(self, clip: Clip) -> tuple[dict[str, np.ndarray], np.ndarray, Camera]:
        """(params per modality (T, D), identity (P,), camera) of a clip."""
        path = self.root / clip.media
        if not path.exists():
            raise FileNotFoundError(f"motion file {path} of clip {clip.id} is missing; regenerate the corpus")
        try:
            with open_npz(path) as data:
                params = {k.removeprefix("param__"): data[k] for k in data.files if k.startswith("param__")}
                identity, camera = data["identity"], Camera.from_dict(json.loads(str(data["camera"])))
        except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError) as exc:
            raise ValueError(f"motion file {path} of clip {clip.id} is corrupt ({exc}); regenerate the corpus") from exc
        return params, identity, camera


@dataclass(frozen=True)
class SyntheticOptions:
    """The synthetic corpus is configured where it is generated (``corpus`` in params.yaml); nothing here."""


class SyntheticAdapter(CorpusAdapter):
    """The embedded synthetic corpus behind the adapter interface (media = ground-truth motion ``.npz``)."""

    name = "synthetic"
    config_type = SyntheticOptions

    def listing(self) -> Listing:
        clips = tuple(dataclasses.replace(c, extra=with_kind("synthetic") + c.extra)
                      for c in SyntheticCorpus(self.root).clips())
        return Listing(clips, ())
