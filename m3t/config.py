"""params.yaml -> frozen dataclasses, one per section, each owned by the component it configures.

``load_params("params.yaml", preset="tiny")`` reads the file, overlays a preset from ``m3t/presets/``
(``tiny`` for tests, ``paper`` for the papers' hyper-parameters; ``default`` is params.yaml itself), and
checks every key and type: an unknown key or a wrong type stops with a message naming ``section.key`` and
what is allowed. Components receive only their own section (``params.fitting``), never the whole tree.
"""
from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Literal, get_args, get_origin

import yaml

from m3t.backtranslation.config import BackTranslationConfig, BackTranslationTrainConfig
from m3t.body.config import BodyConfig
from m3t.corpora.base import CORPORA, CorpusSource, adapter_class
from m3t.corpora.config import SyntheticCorpusConfig
from m3t.experiment import ExperimentConfig
from m3t.fitting.config import FitCorpusConfig, FitJob, FittingConfig, FusionConfig
from m3t.sgsa.config import SGSAConfig, SGSAEvaluateConfig, SGSATrainConfig
from m3t.shards.folders import DataConfig
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
    corpora: dict[str, CorpusSource]  # corpus name -> where it lives and its adapter's options

    def fit_job(self, corpus: str | None = None) -> FitJob:
        """The fit-corpus job of ``corpus`` (default ``fit_corpus.default_corpus``)."""
        name = corpus or self.fit_corpus.default_corpus
        if name not in CORPORA:
            raise ConfigError(f"corpus {name!r} unknown; expected one of {', '.join(CORPORA)}")
        if name not in self.corpora:
            raise ConfigError(f"corpora.{name} is not in params.yaml; add it with root and options "
                              "(see the commented examples there)")
        return FitJob(name, self.corpora[name], str(self.data.shards_dir(name)), self.fit_corpus, self.body,
                      self.fitting, self.tracker, self.mediapipe, self.fusion)


_HINTS = typing.get_type_hints(Params)
SECTIONS: dict[str, Any] = {f.name: _HINTS[f.name] for f in fields(Params)}  # section -> its config class


def _type_name(tp: Any) -> str:
    if get_origin(tp) is Literal:
        return "one of " + ", ".join(repr(a) for a in get_args(tp))
    return getattr(tp, "__name__", str(tp))


def _coerce(value: Any, tp: Any, where: str) -> Any:
    """Check ``value`` against the annotation ``tp``; return it converted (lists -> tuples, int -> float)."""
    origin = get_origin(tp)
    if tp is Any:  # only adapter options: checked against the adapter's own dataclass (_check_corpora)
        return value
    if dataclasses.is_dataclass(tp):
        return build_section(tp, value, where)
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping, got {type(value).__name__} {value!r}")
        key_tp, value_tp = get_args(tp)
        return {_coerce(k, key_tp, f"{where} key {k!r}"): _coerce(v, value_tp, f"{where}.{k}") for k, v in value.items()}
    if origin is Literal:
        if value not in get_args(tp):
            raise ConfigError(f"{where}: {value!r} is not allowed; expected {_type_name(tp)}")
        return value
    if origin in (typing.Union, types.UnionType):
        args = get_args(tp)
        if value is None and type(None) in args:
            return None
        for arg in (a for a in args if a is not type(None)):
            try:
                return _coerce(value, arg, where)
            except ConfigError:
                continue
        raise ConfigError(f"{where}: {value!r} matches none of {[_type_name(a) for a in args]}")
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {type(value).__name__} {value!r}")
        args = get_args(tp)
        item_tp = args[0] if len(args) == 2 and args[1] is Ellipsis else None
        if item_tp is None and len(args) != len(value):
            raise ConfigError(f"{where}: expected {len(args)} items, got {len(value)}")
        return tuple(
            _coerce(v, item_tp if item_tp is not None else args[i], f"{where}[{i}]") for i, v in enumerate(value)
        )
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {type(value).__name__} {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {type(value).__name__} {value!r}")
        return value
    if tp in (str, bool):
        if not isinstance(value, tp):
            raise ConfigError(f"{where}: expected {tp.__name__}, got {type(value).__name__} {value!r}")
        return value
    raise ConfigError(f"{where}: unsupported annotation {tp!r}")  # a bug in a config class, not in the file


def build_section(cls: type, values: dict | None, section: str) -> Any:
    """Build one section's dataclass from a mapping, rejecting unknown keys and wrong types."""
    values = values or {}
    if not isinstance(values, dict):
        raise ConfigError(f"{section}: expected a mapping of keys, got {type(values).__name__}")
    hints = typing.get_type_hints(cls)
    allowed = [f.name for f in fields(cls)]
    unknown = sorted(set(values) - set(allowed))
    if unknown:
        raise ConfigError(f"unknown key(s) {', '.join(f'{section}.{k}' for k in unknown)}; allowed keys in '{section}': {', '.join(allowed)}")
    kwargs = {k: _coerce(v, hints[k], f"{section}.{k}") for k, v in values.items()}
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except ValueError as exc:  # a section's own consistency check (__post_init__)
        raise ConfigError(f"{section}: {exc}") from exc


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
            raise ConfigError(f"corpora.{name}: expected a mapping with root and options; got {entry!r}")
        entry = dict(entry or {})
        if "shards_dir" in entry:
            raise ConfigError(f"corpora.{name}.shards_dir: shard folders are derived as data.shards_root/{name}; "
                              "remove the key (set data.shards_root to move every corpus' shards)")
        options = entry.get("options") or {}
        if not isinstance(options, dict):
            raise ConfigError(f"corpora.{name}.options: expected a mapping, got {type(options).__name__}")
        built = build_section(adapter_class(name).config_type, options, f"corpora.{name}.options")
        out[name] = {**entry, "options": {k: getattr(built, k) for k in options}}
    training = (raw.get("data") or {}).get("train_corpora", DataConfig.train_corpora)
    missing = [c for c in (training or []) if c not in out]
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


def read_yaml(path: str | Path) -> dict:
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"params file {path} not found; run from the repository root or pass its path")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
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
    unknown = sorted(set(raw) - set(SECTIONS))
    if unknown:
        raise ConfigError(f"unknown section(s) {', '.join(unknown)}; allowed sections: {', '.join(SECTIONS)}")
    raw = {**raw, "corpora": _check_corpora(raw)}
    return Params(**{name: _coerce(raw.get(name) or {}, _HINTS[name], name) for name in SECTIONS})


def load_params(path: str | Path = "params.yaml", preset: str = "default", overrides: dict | None = None) -> Params:
    """Read params.yaml, overlay a preset and optional overrides, and validate every section."""
    raw = merge(merge(read_yaml(path), preset_overlay(preset)), overrides or {})
    return params_from_dict(raw)
