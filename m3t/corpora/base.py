"""The corpus adapters' base class and registry: :func:`open_corpus` opens corpus ``name`` at a root with its
options, :class:`CorpusSource` says where one corpus lives (params.yaml ``corpora.<name>``).

What an adapter's listing is made of (clips, quarantined rows, media checks) is in :mod:`m3t.corpora.listing`;
safe readers of annotation files in :mod:`m3t.corpora.annotation_files`; split helpers in
:mod:`m3t.corpora.splits`.
"""
from __future__ import annotations

import dataclasses
import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from m3t.corpora.clip import Clip
from m3t.corpora.listing import Listing
from m3t.dataclass_io import build_dataclass


class CorpusAdapter:
    """Base of every adapter: ``listing()`` does the work, ``clips()`` keeps only the listed clips."""

    name: ClassVar[str] = ""
    config_type: ClassVar[type] = type(None)

    def __init__(self, root: str | Path, config: Any = None):
        self.root = Path(root)
        self.config = config if config is not None else self.config_type()

    def listing(self) -> Listing:
        raise NotImplementedError

    def clips(self) -> tuple[Clip, ...]:
        return self.listing().clips


_ADAPTERS = {
    "synthetic": "m3t.corpora.synthetic_storage:SyntheticAdapter",
    "phoenix14t": "m3t.corpora.phoenix14t:Phoenix14TCorpus",
    "how2sign": "m3t.corpora.how2sign:How2SignCorpus",
    "csl_daily": "m3t.corpora.csl_daily:CslDailyCorpus",
    "nmfs_csl": "m3t.corpora.nmfs_csl:NmfsCslCorpus",
    "mead": "m3t.corpora.mead:MeadCorpus",
    "soke_smplx": "m3t.corpora.soke_smplx:SokeSmplxCorpus",
    "slt_pickle": "m3t.corpora.slt_pickle:SltPickleCorpus",
    "posefile": "m3t.corpora.posefile:PoseFileCorpus",
    "fingerspelling": "m3t.corpora.fingerspelling:FingerspellingCorpus",
}
CORPORA: tuple[str, ...] = tuple(_ADAPTERS)


@dataclass(frozen=True)
class CorpusSource:
    """Where one corpus lives (params.yaml ``corpora.<name>``). ``root`` "" = the adapter's default (the
    fingerspelling lexicon inside its installed package); ``options`` = the adapter's option dataclass fields.
    Its shards go to ``data.shards_root/<name>`` (:class:`m3t.shards.folders.DataConfig`)."""

    root: str = ""
    options: dict[str, Any] = dataclasses.field(default_factory=dict)


def adapter_class(name: str) -> type[CorpusAdapter]:
    if name not in _ADAPTERS:
        raise ValueError(f"corpus {name!r} unknown; expected one of {', '.join(CORPORA)}")
    module, cls = _ADAPTERS[name].split(":")
    return getattr(importlib.import_module(module), cls)  # imported on demand: adapters import this module


def open_corpus(name: str, root: str | Path | None, **options: Any) -> CorpusAdapter:
    """The adapter for corpus ``name`` at ``root``; ``options`` are the fields of its option dataclass.

    Options are type-checked (lists from YAML become tuples where the option is a tuple); unknown or wrongly
    typed options raise ``ValueError`` naming the allowed ones or the option.
    """
    cls = adapter_class(name)
    fields = {f.name: f for f in dataclasses.fields(cls.config_type)}
    unknown = sorted(set(options) - set(fields))
    if unknown:
        raise ValueError(f"corpora.{name}: unknown options {unknown}; allowed: {', '.join(fields) or 'none'}")
    return cls(root if root is not None else "", build_dataclass(cls.config_type, options, f"corpora.{name}.options"))
