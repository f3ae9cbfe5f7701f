"""The plan of ``m3t study``: every step (a variant's stage) the papers' claims need, in run order, and the params
file of each variant.

Where the study writes (nothing outside ``root``): ``<root>/params/<variant>.yaml`` (params.yaml + the preset,
every output folder redirected under ``root``); the shared corpus, shards, tokens, models and metrics under
``<root>/data``, ``<root>/models``, ``<root>/metrics``; each variant's own models, generated motion and metrics
under ``<root>/variants/<variant>/``, whose models folder holds relative links to the shared models it reads. The
caches (``*.cache_dir``) stay where params.yaml puts them: they are content-addressed and shared.

Order matters to the claims: :func:`m3t.claims.collectors.sgsa_systems` reads the setting of the newest evaluate-sgsa run, so
every SGSA N = inf step comes before the default-adjacency ones, and those are evaluated again whenever an N = inf
evaluation ran (their ``after``).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import yaml

from m3t.atomic import write_text
from m3t.config import Params, merge, params_from_dict, preset_overlay, read_yaml
from m3t.experiment import to_dict

SHARED = "shared"
# (quantizer, batch size) of M3T Tab. 3's claims: FSQ against the three VQs, and FSQ at batch 128
TOKENIZER_SETTINGS = (("fsq", 16), ("vq", 16), ("vq_ema", 16), ("vq_plain", 16), ("fsq", 128))


class StudyError(ValueError):
    """A study that cannot be planned or run as asked; the message names the file, key or step."""


@dataclass(frozen=True)
class Step:
    variant: str
    stage: str
    params: Path  # the variant's params file
    argv: tuple[str, ...]
    deps: tuple[str, ...] = ()  # names of the steps whose outputs it reads: their failure skips it
    links: tuple[tuple[Path, Path], ...] = ()  # (link, shared target) made right before it runs
    after: tuple[str, ...] = ()  # it reruns whenever one of these ran (ordering for the claims, not a dependency)

    @property
    def name(self) -> str:
        return f"{self.variant}.{self.stage}"


def _argv(module: str, params: Path, *extra: str) -> tuple[str, ...]:
    return ("python", "-m", f"m3t.stages.{module}", "--params", str(params), *extra)


def _folders(root: Path, variant: str) -> dict:
    """The output keys of a variant's params, all under ``root`` (the shared ones for ``shared``)."""
    own = root if variant == SHARED else root / "variants" / variant
    return {"data": {"shards_root": str(root / "data" / "shards"), "tokens_root": str(root / "data" / "tokens"),
                     "models_dir": str(own / "models"),
                     "generated_dir": str(root / "data" / "generated" if variant == SHARED else own / "generated"),
                     "metrics_dir": str(own / "metrics")},
            "corpora": {"synthetic": {"root": str(root / "data" / "corpus" / "synthetic")}},
            "experiment": {"dashboard_dir": str(root / "dashboards")}}


class _Writer:
    """Writes ``<root>/params/<variant>.yaml``: the base tree, the variant's settings, its folders."""

    def __init__(self, raw: dict, root: Path, source: str):
        self.raw, self.root, self.source = raw, root, source

    def write(self, variant: str, settings: dict) -> tuple[Path, Params]:
        tree = merge(merge(self.raw, settings), _folders(self.root, variant))
        params = params_from_dict(tree)
        path = self.root / "params" / f"{variant}.yaml"
        write_text(path, f"# m3t study, variant {variant}: {self.source}; rewritten by `m3t study`\n"
                         + yaml.safe_dump(to_dict(params), sort_keys=False))
        return path, params


def _check(base: Params, where: str, seeds: Sequence[int]) -> None:
    if not seeds or len(set(seeds)) != len(seeds):
        raise StudyError(f"seeds {list(seeds)}: give at least one seed, each once")
    if base.sgsa.decoder_layers == 0:
        raise StudyError(f"{where}: sgsa.decoder_layers is 0 (that is PT); the SGSA claims need SGSA layers")
    if base.sgsa.temporal_adjacency == 0:
        raise StudyError(f"{where}: sgsa.temporal_adjacency is 0 (N = inf); the adjacency claim compares N = inf "
                         "with the configured finite N: set it to 1 (the paper's best)")


class _Planner:
    """Collects the steps in run order, one family of variants at a time; ``shared.*`` names the shared steps."""

    def __init__(self, raw: dict, base: Params, root: Path, where: str):
        self.base, self.root, self.writer = base, root, _Writer(raw, root, where)
        self.steps: list[Step] = []
        self.shared_seed = base.tokenizer_train.seed  # the configured tokenizers: tokenize and every model read them
        self.path, self.shared = self.writer.write(SHARED, {"tokenizer": {"quantizer": "fsq"}, "tokenizer_train": {
            "batch_size": 16, "seed": self.shared_seed}})
        self.fits: tuple[str, ...] = ()
        self.tok = f"{SHARED}.train-tokenizers"

    def add_shared(self) -> None:
        p, s = self.path, f"{SHARED}."
        corpora = list(dict.fromkeys((*self.base.data.train_corpora, self.base.slr.corpus)))
        if "synthetic" in corpora:
            self.steps.append(Step(SHARED, "generate-corpus", p, _argv("generate_corpus", p)))
        for corpus in corpora:
            stage = "fit-corpus" if corpus == "synthetic" else f"fit-corpus-{corpus}"
            deps = (s + "generate-corpus",) if corpus == "synthetic" else ()
            self.steps.append(Step(SHARED, stage, p, _argv("fit_corpus", p, "--corpus", corpus), deps))
        fits = self.fits = tuple(st.name for st in self.steps if st.stage.startswith("fit-corpus"))
        self.steps += [Step(SHARED, "train-tokenizers", p, _argv("train_tokenizers", p), fits),
                       Step(SHARED, "tokenize", p, _argv("tokenize", p), (self.tok, *fits)),
                       Step(SHARED, "train-backtranslation", p, _argv("train_backtranslation", p), fits),
                       Step(SHARED, "evaluate-backtranslation", p, _argv("evaluate_backtranslation", p),
                            (s + "train-backtranslation",)),
                       Step(SHARED, "train-backtranslation-skeleton", p, _argv("train_backtranslation_skeleton", p),
                            fits)]

    def add(self, name: str, settings: dict, stages: Sequence[tuple[str, tuple[str, ...]]],
            shared_dirs: Sequence[str] = (), generated_from: str | None = None,
            after: Mapping[str, tuple[str, ...]] | None = None) -> None:
        """A variant's steps; its models folder links ``shared_dirs`` (DataConfig properties) of the shared models,
        its generated folder is that of the variant ``generated_from``."""
        path, params = self.writer.write(name, settings)
        links = tuple((getattr(params.data, d), getattr(self.shared.data, d)) for d in shared_dirs)
        if generated_from is not None:
            source = _folders(self.root, generated_from)["data"]["generated_dir"]
            links += ((Path(params.data.generated_dir), Path(source)),)
        self.steps.extend(Step(name, stage, path, _argv(stage.replace("-", "_"), path), deps, links,
                               (after or {}).get(stage, ())) for stage, deps in stages)

    def add_tokenizers(self, seed: int) -> None:
        for quantizer, batch in TOKENIZER_SETTINGS:
            if (quantizer, batch, seed) != ("fsq", 16, self.shared_seed):  # that one is the shared run
                self.add(f"tokenizer-{quantizer}-b{batch}-s{seed}", {"tokenizer": {"quantizer": quantizer},
                         "tokenizer_train": {"batch_size": batch, "seed": seed}}, [("train-tokenizers", self.fits)])

    def add_smlm(self, seed: int) -> None:
        tokens = (f"{SHARED}.tokenize", self.tok)
        # the objective's ablation at equal epochs (shared steps) and at equal production updates (added steps)
        for objective, steps, kind in ((True, "shared", "translation"), (False, "shared", "production"),
                                       (True, "added", "translation-added")):
            name = f"smlm-{kind}-s{seed}"
            self.add(name, {"smlm_train": {"translation_objective": objective, "translation_steps": steps,
                                           "seed": seed}},
                     [("train-smlm", tokens), ("generate-smlm", (f"{name}.train-smlm", *tokens)),
                      ("evaluate-smlm", (f"{name}.generate-smlm", f"{SHARED}.train-backtranslation"))],
                     ("tokenizers_dir", "backtranslation_dir"))

    def add_slr(self, seed: int) -> None:
        self.add(f"slr-s{seed}", {"slr_train": {"seed": seed}},
                 [("train-slr", (*self.fits, self.tok)), ("evaluate-slr", (f"slr-s{seed}.train-slr", self.tok))],
                 ("tokenizers_dir",))

    def add_sgsa(self, seed: int, infinite: bool) -> None:
        """N = inf (the SGSA system alone), or the configured N beside PT, judged with the same seed's SMLM."""
        judge, dirs = (f"{SHARED}.train-backtranslation-skeleton", self.tok), ("tokenizers_dir", "skeleton_judge_dir")
        if infinite:
            name = f"sgsa-ninf-s{seed}"
            self.add(name, {"sgsa": {"temporal_adjacency": 0}, "sgsa_train": {"systems": ["sgsa"], "seed": seed}},
                     [("train-sgsa", self.fits), ("evaluate-sgsa", (f"{name}.train-sgsa", *judge))], dirs)
            return
        name, smlm = f"sgsa-n{self.base.sgsa.temporal_adjacency}-s{seed}", f"smlm-translation-s{seed}"
        inf = tuple(st.name for st in self.steps if st.variant.startswith("sgsa-ninf-") and st.stage == "evaluate-sgsa")
        evaluate = ("evaluate-sgsa", (f"{name}.train-sgsa", *judge, f"{smlm}.generate-smlm"))
        self.add(name, {"sgsa_train": {"systems": ["pt", "sgsa"], "seed": seed}}, [("train-sgsa", self.fits), evaluate],
                 dirs, generated_from=smlm, after={"evaluate-sgsa": inf})


def plan(params_path: str | Path, preset: str, seeds: Sequence[int], root: str | Path) -> list[Step]:
    """Every step of the study in run order; writes the variants' params files under ``<root>/params``."""
    where = f"{params_path} + preset {preset}"
    raw = merge(read_yaml(params_path), preset_overlay(preset))
    base = params_from_dict(raw)
    _check(base, where, seeds)
    planner = _Planner(raw, base, Path(root), where)
    planner.add_shared()
    for add in (planner.add_tokenizers, planner.add_smlm, planner.add_slr):
        for seed in seeds:
            add(seed)
    for infinite in (True, False):  # every N = inf run first: the claims read the setting of the newest evaluate-sgsa
        for seed in seeds:
            planner.add_sgsa(seed, infinite)
    return planner.steps


def select(steps: list[Step], only: Sequence[str]) -> list[Step]:
    """The steps named by stage, variant or ``variant.stage`` in ``only`` (all when empty)."""
    unknown = [n for n in only if not any(n in (st.stage, st.variant, st.name) for st in steps)]
    if unknown:
        stages = ", ".join(dict.fromkeys(st.stage for st in steps))
        raise StudyError(f"--only {' '.join(unknown)}: no step of the plan is named so; give stages ({stages}), "
                         "variants (e.g. slr-s0) or variant.stage")
    return [st for st in steps if not only or any(n in (st.stage, st.variant, st.name) for n in only)]

