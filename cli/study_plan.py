"""The plan of ``m3t study``: every variant the papers' claims (:mod:`m3t.claims`) need, for every seed, as DVC
experiments (:class:`cli.variants.Variant`), in run order.

A variant names its settings and the ``dvc.yaml`` stages whose MLflow runs the claims read; nothing here says what
those stages read: DVC runs whatever they need, and its run cache restores what another variant already ran with
the same settings (the corpus, its fits, the shared tokenizers, the SMLM a SGSA variant is judged beside). Every
variant reads the same tokenizers (:data:`SHARED`, the configured seed); the tokenizer variants train their own
beside them.

Variants, per seed ``s``: ``tokenizer-<q>-b<batch>-s<s>`` (M3T Tab. 3), ``smlm-{translation,production,
translation-added}-s<s>`` (the objective's ablation at equal epochs and at equal production updates),
``slr-s<s>`` (the probe with and without the face), ``sgsa-ninf-s<s>`` (SGSA at N = inf) and ``sgsa-n<N>-s<s>``
(PT and SGSA at the configured N, judged beside the same seed's SMLM); ``shared`` first (the shared tokenizers and
the back-translation judges, and the baselines, which read no trained production model).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

from cli.variants import Variant, VariantError
from m3t.config import Params

# (quantizer, batch size) of M3T Tab. 3's claims: FSQ against the three VQs, and FSQ at batch 128
TOKENIZER_SETTINGS = (("fsq", 16), ("vq", 16), ("vq_ema", 16), ("vq_plain", 16), ("fsq", 128))
SHARED = {"tokenizer.quantizer": "fsq", "tokenizer_train.batch_size": 16}  # the tokenizers every model reads
# (name, translation_objective, translation_steps) of the SMLM objective's ablation
SMLM_KINDS = (("translation", True, "shared"), ("production", False, "shared"), ("translation-added", True, "added"))


class StudyError(VariantError):
    """A study that cannot be planned or run as asked; the message names the file, key or variant."""


def check(base: Params, where: str, seeds: Sequence[int]) -> None:
    if not seeds or len(set(seeds)) != len(seeds):
        raise StudyError(f"seeds {list(seeds)}: give at least one seed, each once")
    if base.sgsa.decoder_layers == 0:
        raise StudyError(f"{where}: sgsa.decoder_layers is 0 (that is PT); the SGSA claims need SGSA layers")
    if base.sgsa.temporal_adjacency == 0:
        raise StudyError(f"{where}: sgsa.temporal_adjacency is 0 (N = inf); the adjacency claim compares N = inf "
                         "with the configured finite N: set it to 1 (the paper's best)")


def _smlm(kind: str, seed: int) -> dict[str, object]:
    _, objective, steps = next(k for k in SMLM_KINDS if k[0] == kind)
    return {"smlm_train.translation_objective": objective, "smlm_train.translation_steps": steps,
            "smlm_train.seed": seed}


def plan(base: Params, seeds: Sequence[int], where: str = "params.yaml") -> list[Variant]:
    """Every variant of the study in run order (module docstring); ``base`` is the params with the preset."""
    check(base, where, seeds)
    shared_seed = base.tokenizer_train.seed
    shared = {**SHARED, "tokenizer_train.seed": shared_seed}
    out = [Variant("shared", shared, ("evaluate-backtranslation", "train-backtranslation-skeleton",
                                      "evaluate-baselines"))]
    for seed in seeds:
        out += [Variant(f"tokenizer-{q}-b{b}-s{seed}", {"tokenizer.quantizer": q, "tokenizer_train.batch_size": b,
                                                         "tokenizer_train.seed": seed}, ("train-tokenizers",))
                for q, b in TOKENIZER_SETTINGS if (q, b, seed) != ("fsq", 16, shared_seed)]
    for seed in seeds:
        out += [Variant(f"smlm-{kind}-s{seed}", {**shared, **_smlm(kind, seed)}, ("evaluate-smlm",))
                for kind, _, _ in SMLM_KINDS]
    out += [Variant(f"slr-s{seed}", {**shared, "slr_train.seed": seed}, ("evaluate-slr",)) for seed in seeds]
    adjacency = base.sgsa.temporal_adjacency
    for name, settings in (("sgsa-ninf-s{}", {"sgsa.temporal_adjacency": 0, "sgsa_train.systems": ["sgsa"]}),
                           (f"sgsa-n{adjacency}-s{{}}", {"sgsa_train.systems": ["pt", "sgsa"]})):
        out += [Variant(name.format(seed), {**shared, **_smlm("translation", seed), **settings,
                                            "sgsa_train.seed": seed}, ("evaluate-sgsa",)) for seed in seeds]
    return out


def family(variant: Variant) -> str:
    """``tokenizer``, ``smlm``, ``slr``, ``sgsa`` or ``shared``."""
    return variant.name.split("-", 1)[0]


def select(variants: list[Variant], only: Sequence[str]) -> list[Variant]:
    """The variants named in ``only`` by name, family (``sgsa``: every SGSA variant) or stage (all when empty)."""
    def named(v: Variant, n: str) -> bool:
        return n in (v.name, family(v)) or n in v.targets

    unknown = [n for n in only if not any(named(v, n) for v in variants)]
    if unknown:
        families = ", ".join(dict.fromkeys(family(v) for v in variants))
        raise StudyError(f"--only {' '.join(unknown)}: no variant of the plan is named so; give families "
                         f"({families}), stages (e.g. evaluate-sgsa) or variants (e.g. slr-s0)")
    return [v for v in variants if not only or any(named(v, n) for n in only)]


def parse_settings(pairs: Sequence[str]) -> dict[str, object]:
    """``KEY=VALUE`` pairs (the value read as YAML) -> settings for every variant."""
    import yaml

    out: dict[str, object] = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key.strip():
            raise StudyError(f"--set {pair!r}: expected KEY=VALUE, e.g. sgsa_evaluate.counter=ground_truth")
        out[key.strip()] = yaml.safe_load(value)
    return out


def with_settings(variants: list[Variant], settings: Mapping[str, object]) -> list[Variant]:
    """Every variant with ``settings`` added (its own settings win a clash: the study's axes stay what they are)."""
    return [Variant(v.name, {**settings, **v.settings}, v.targets) for v in variants]
