"""params.yaml -> frozen dataclasses, one per section, each owned by the component it configures.

``load_params("params.yaml", preset="tiny")`` reads the file, overlays a preset from ``m3t/presets/``
(``tiny`` for tests, ``paper`` for the papers' hyper-parameters; ``default`` is params.yaml itself), and
checks every key and type: an unknown key or a wrong type stops with a message naming ``section.key`` and
what is allowed. Components receive only their own section (``params.fitting``), never the whole tree.

Each section's class is named by its import path in :data:`SECTIONS` and imported when params are loaded, not
when this module is: a DVC stage's code deps are then what it runs, so a changed SGSA default reruns the stages
that read ``sgsa`` and not ``generate-corpus`` (``tests/project/test_architecture.py`` checks that every stage
imports the config module of each section it declares in ``dvc.yaml``).
"""
from __future__ import annotations

import importlib
import os
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from m3t.corpora.base import CORPORA, CorpusSource, adapter_class
from m3t.dataclass_io import build_dataclass, coerce, short_repr
from m3t.shards.folders import DataConfig  # imported here: every stage derives its folders from it

if TYPE_CHECKING:  # for readers and type checkers; at run time the classes come from SECTIONS
    from m3t.backtranslation.config import (
        BackTranslationConfig,
        BackTranslationTrainConfig,
    )
    from m3t.body.config import BodyConfig
    from m3t.corpora.config import SyntheticCorpusConfig
    from m3t.experiment import ExperimentConfig
    from m3t.fitting.config import FitCorpusConfig, FitJob, FittingConfig, FusionConfig
    from m3t.production.config import BaselinesConfig
    from m3t.sgsa.config import SGSAConfig, SGSAEvaluateConfig, SGSATrainConfig
    from m3t.slr.config import SLRConfig, SLREvaluateConfig, SLRTrainConfig
    from m3t.smlm.config import GenerateConfig, SMLMConfig, SMLMTrainConfig
    from m3t.tokenizers.config import TokenizerConfig, TokenizerTrainConfig
    from m3t.trackers.config import MediaPipeConfig, SimulatedTrackerConfig

PRESET_DIR = Path(__file__).parent / "presets"
PRESETS = ("default", "tiny", "paper", "study")


class ConfigError(ValueError):
    """A params file that does not match the dataclasses; the message names the key and the fix."""


@dataclass(frozen=True)
class Params:
    data: DataConfig  # the corpora the downstream stages train on, and every derived folder
    synthetic_corpus: SyntheticCorpusConfig  # the embedded corpus generator
    body: BodyConfig
    tracker: SimulatedTrackerConfig  # simulated 2D tracker of the synthetic corpus
    mediapipe: MediaPipeConfig  # real 2D tracking of videos / frame folders
    fusion: FusionConfig  # NLF / WiLoR / Pixel3DMM outputs -> initialisation
    fitting: FittingConfig
    fit_corpus: FitCorpusConfig
    experiment: ExperimentConfig
    tokenizer: TokenizerConfig
    tokenizer_train: TokenizerTrainConfig
    smlm: SMLMConfig
    smlm_train: SMLMTrainConfig
    smlm_generate: GenerateConfig
    slr: SLRConfig  # recognition probe on frozen tokenizer features, and active-window trimming
    slr_train: SLRTrainConfig
    slr_evaluate: SLREvaluateConfig
    backtranslation: BackTranslationConfig  # the sign-to-text judge of every production model
    backtranslation_train: BackTranslationTrainConfig
    sgsa: SGSAConfig  # skeletal graph self-attention production (SGSA) and its PT baseline
    sgsa_train: SGSATrainConfig
    sgsa_evaluate: SGSAEvaluateConfig
    baselines: BaselinesConfig  # the copy baselines scored beside the models (retrieval, lexicon)
    corpora: dict[str, CorpusSource]  # corpus name -> where it lives and its adapter's options

    def fit_job(self, corpus: str | None = None) -> FitJob:
        """The fit-corpus job of ``corpus`` (default ``fit_corpus.default_corpus``)."""
        name = corpus or self.fit_corpus.default_corpus
        if name not in CORPORA:
            raise ConfigError(f"corpus {name!r} unknown; expected one of {', '.join(CORPORA)}")
        if name not in self.corpora:
            raise ConfigError(f"corpora.{name} is not in params.yaml; add it with root and options "
                              "(see the commented examples there)")
        fit_job = _resolve("m3t.fitting.config:FitJob")
        return fit_job(name, self.corpora[name], str(self.data.shards_dir(name)), self.fit_corpus, self.body,
                       self.fitting, self.tracker, self.mediapipe, self.fusion)


# section -> "module:class" of its config dataclass, in params.yaml order; ``corpora`` is checked by
# _check_corpora against each adapter's own options class
SECTIONS: dict[str, str] = {
    "data": "m3t.shards.folders:DataConfig",
    "experiment": "m3t.experiment:ExperimentConfig",
    "synthetic_corpus": "m3t.corpora.config:SyntheticCorpusConfig",
    "body": "m3t.body.config:BodyConfig",
    "tracker": "m3t.trackers.config:SimulatedTrackerConfig",
    "fitting": "m3t.fitting.config:FittingConfig",
    "fit_corpus": "m3t.fitting.config:FitCorpusConfig",
    "mediapipe": "m3t.trackers.config:MediaPipeConfig",
    "fusion": "m3t.fitting.config:FusionConfig",
    "tokenizer": "m3t.tokenizers.config:TokenizerConfig",
    "tokenizer_train": "m3t.tokenizers.config:TokenizerTrainConfig",
    "backtranslation": "m3t.backtranslation.config:BackTranslationConfig",
    "backtranslation_train": "m3t.backtranslation.config:BackTranslationTrainConfig",
    "smlm": "m3t.smlm.config:SMLMConfig",
    "smlm_train": "m3t.smlm.config:SMLMTrainConfig",
    "smlm_generate": "m3t.smlm.config:GenerateConfig",
    "slr": "m3t.slr.config:SLRConfig",
    "slr_train": "m3t.slr.config:SLRTrainConfig",
    "slr_evaluate": "m3t.slr.config:SLREvaluateConfig",
    "sgsa": "m3t.sgsa.config:SGSAConfig",
    "sgsa_train": "m3t.sgsa.config:SGSATrainConfig",
    "sgsa_evaluate": "m3t.sgsa.config:SGSAEvaluateConfig",
    "baselines": "m3t.production.config:BaselinesConfig",
    "corpora": "",
}


@cache
def _resolve(path: str) -> Any:
    module, name = path.split(":")
    return getattr(importlib.import_module(module), name)


def section_class(section: str) -> type:
    """The config dataclass of a params.yaml section (imported on first use)."""
    if not SECTIONS.get(section):
        raise ConfigError(f"no config class for section {section!r}; sections with one: "
                          f"{', '.join(s for s, p in SECTIONS.items() if p)}")
    return _resolve(SECTIONS[section])


def build_section(cls: type, values: dict | None, section: str) -> Any:
    """Build one section's dataclass from a mapping, rejecting unknown keys and wrong types."""
    return build_dataclass(cls, values, section, error=ConfigError)


def _check_corpora(raw: dict) -> dict:
    """``corpora``: known corpus names only, each with ``root`` and ``options``, the options typed by the
    adapter's own option dataclass; ``data.train_corpora`` must name corpora listed here."""
    corpora = raw.get("corpora") or {}
    if not isinstance(corpora, dict):
        raise ConfigError(f"corpora: expected a mapping of corpus names, got {type(corpora).__name__}")
    out = {}
    for name, entry in corpora.items():
        if name not in CORPORA:
            raise ConfigError(f"unknown corpus corpora.{name}; allowed corpora: {', '.join(CORPORA)}")
        if not isinstance(entry, (dict, type(None))):
            raise ConfigError(f"corpora.{name}: expected a mapping with root and options; got {short_repr(entry)}")
        entry = dict(entry or {})
        if "shards_dir" in entry:
            raise ConfigError(f"corpora.{name}.shards_dir: shard folders are derived as data.shards_root/{name}; "
                              "remove the key (set data.shards_root to move every corpus' shards)")
        options = entry.get("options") or {}
        if not isinstance(options, dict):
            raise ConfigError(f"corpora.{name}.options: expected a mapping, got {type(options).__name__}")
        built = build_section(adapter_class(name).config_type, options, f"corpora.{name}.options")
        out[name] = {**entry, "options": {k: getattr(built, k) for k in options}}
    data = raw.get("data") or {}
    training = data.get("train_corpora", section_class("data").train_corpora) if isinstance(data, dict) else ()
    if not isinstance(training, (list, tuple)) or not all(isinstance(c, str) for c in training):
        training = ()  # not a list of names: the data section's own check names the key
    missing = [c for c in training if c not in out]
    if missing:
        raise ConfigError(f"data.train_corpora names {', '.join(missing)}, not listed in corpora; add "
                          f"corpora.{missing[0]} (root, options) or remove it from data.train_corpora")
    return out


def merge(base: dict, overlay: dict) -> dict:
    """Recursive dict merge; overlay wins."""
    out = dict(base)
    for key, value in overlay.items():
        out[key] = merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


MAX_NODES_ENV = "M3T_YAML_MAX_NODES"
MAX_NODES = 1_000_000  # values a params file may hold once its aliases are expanded (params.yaml holds ~1,000)
MAX_BYTES_ENV = "M3T_YAML_MAX_BYTES"
MAX_BYTES = 16 * 2**20  # a params file's size (params.yaml is ~20 kB)
MAX_DEPTH_ENV = "M3T_YAML_MAX_DEPTH"
MAX_DEPTH = 100  # nested collections (params.yaml nests 4 deep); PyYAML's scanner slows with depth, then recursion ends it


class _TooDeep(Exception):
    pass


class _BoundedLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that stops composing past ``max_depth`` nested collections (a file of 50,000 nested
    lists otherwise costs seconds of scanning before Python's recursion limit ends it)."""

    max_depth = MAX_DEPTH

    def __init__(self, stream):
        super().__init__(stream)
        self.depth = 0

    def compose_node(self, parent, index):
        self.depth += 1
        try:
            if self.depth > self.max_depth:
                raise _TooDeep
            return super().compose_node(parent, index)
        finally:
            self.depth -= 1


def _expanded_nodes(node: yaml.Node, memo: dict[int, int]) -> int:
    """How many nodes ``node`` becomes when every alias is expanded, counted without expanding (an alias is a
    shared node: its count is remembered, so a file of nested aliases is counted in a pass over its nodes)."""
    key = id(node)
    if key not in memo:
        memo[key] = 1  # a recursive alias counts once instead of forever
        if isinstance(node, yaml.SequenceNode):
            memo[key] = 1 + sum(_expanded_nodes(n, memo) for n in node.value)
        elif isinstance(node, yaml.MappingNode):
            memo[key] = 1 + sum(_expanded_nodes(k, memo) + _expanded_nodes(v, memo) for k, v in node.value)
    return memo[key]


def safe_yaml(text: str, where: str | Path) -> object:
    """``yaml.safe_load`` with the expansion of aliases bounded: a file whose aliases would expand to more than
    ``M3T_YAML_MAX_NODES`` values (default :data:`MAX_NODES`) is refused before anything is built."""
    limit = int(os.environ.get(MAX_NODES_ENV) or MAX_NODES)
    loader = _BoundedLoader(text)
    loader.max_depth = int(os.environ.get(MAX_DEPTH_ENV) or MAX_DEPTH)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        nodes = _expanded_nodes(node, {})
        if nodes > limit:
            raise ConfigError(f"{where}: its aliases expand to {nodes:,} values, more than {limit:,} (a YAML alias "
                              f"bomb?); a legitimately large file: raise {MAX_NODES_ENV}")
        return loader.construct_document(node)
    except (RecursionError, _TooDeep):
        raise ConfigError(f"{where}: nested too deeply to read (more than {loader.max_depth} levels); a legitimately "
                          f"deep file: raise {MAX_DEPTH_ENV}") from None
    finally:
        loader.dispose()


def read_yaml(path: str | Path) -> dict:
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"params file {path} not found; run from the repository root or pass its path")
    size, limit = path.stat().st_size, int(os.environ.get(MAX_BYTES_ENV) or MAX_BYTES)
    if size > limit:
        raise ConfigError(f"{path}: {size:,} bytes, more than {limit:,} (a params file is tens of kB); a legitimately "
                          f"large file: raise {MAX_BYTES_ENV}")
    try:
        data = safe_yaml(path.read_text(encoding="utf-8"), path) or {}
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start}); re-save it as UTF-8") from exc
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc}); fix the line shown") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of sections at top level")
    return data


def preset_overlay(preset: str) -> dict:
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; allowed: {', '.join(PRESETS)}")
    return {} if preset == "default" else read_yaml(PRESET_DIR / f"{preset}.yaml")


def params_from_dict(raw: dict) -> Params:
    unknown = sorted(map(str, set(raw) - set(SECTIONS)))  # YAML keys may be numbers or null
    if unknown:
        raise ConfigError(f"unknown section(s) {', '.join(unknown)}; allowed sections: {', '.join(SECTIONS)}")
    raw = {**raw, "corpora": _check_corpora(raw)}
    built = {name: coerce(raw.get(name) or {}, section_class(name), name, ConfigError)
             for name in SECTIONS if name != "corpora"}
    corpora = coerce(raw["corpora"], dict[str, CorpusSource], "corpora", ConfigError)
    return Params(**built, corpora=corpora)


def load_params(path: str | Path = "params.yaml", preset: str = "default", overrides: dict | None = None) -> Params:
    """Read params.yaml, overlay a preset and optional overrides, and validate every section."""
    raw = merge(merge(read_yaml(path), preset_overlay(preset)), overrides or {})
    return params_from_dict(raw)
