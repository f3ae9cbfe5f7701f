"""The plan of ``m3t study``: every step (a variant's stage) the papers' claims need, in run order, and the params
file of each variant.

Where the study writes (nothing outside ``root``): ``<root>/params/<variant>.yaml`` (params.yaml + the preset,
every output folder redirected under ``root``); the shared corpus, shards, tokens, models and metrics under
``<root>/data``, ``<root>/models``, ``<root>/metrics``; each variant's own models, generated motion and metrics
under ``<root>/variants/<variant>/``, whose models folder holds relative links to the shared models it reads. The
caches (``*.cache_dir``) stay where params.yaml puts them: they are content-addressed and shared.

What each step reads is not declared here: :func:`stage_graph` derives it from ``dvc.yaml`` (a stage reads another
when one of its deps is, or lies inside, one of the other's outputs), and each step runs its stage's ``cmd`` with
``--params`` of its variant. A variant reads a stage it does not run from the shared steps, or from the variant it
takes its generated motion from. Only the corpus fits are the study's own: it fits every corpus it trains or
probes on, where ``dvc.yaml`` has one fit stage per corpus of the embedded default.

Order matters to the claims: :func:`m3t.claims.collectors.sgsa_systems` reads the setting of the newest evaluate-sgsa run, so
every SGSA N = inf step comes before the default-adjacency ones, and those are evaluated again whenever an N = inf
evaluation ran (their ``after``).
"""
from __future__ import annotations

import shlex
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import yaml

from m3t.atomic import write_text
from m3t.config import Params, merge, params_from_dict, preset_overlay, read_yaml
from m3t.experiment import to_dict

SHARED = "shared"
DVC_YAML = Path(__file__).resolve().parents[1] / "dvc.yaml"
FIT = "fit-corpus"  # dvc.yaml's fit stage stands for every corpus fit of the study
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


@dataclass(frozen=True)
class StageGraph:
    reads: dict[str, tuple[str, ...]]  # stage -> the stages whose outputs it reads, in dvc.yaml order
    cmd: dict[str, tuple[str, ...]]  # stage -> its command line


def _paths(entries: Sequence) -> list[str]:
    return [str(e if isinstance(e, str) else next(iter(e))) for e in entries or ()]


@cache
def stage_graph(path: Path = DVC_YAML) -> StageGraph:
    """What each ``dvc.yaml`` stage reads: a stage reads another when one of its deps equals, lies inside or holds
    one of the other's outputs (``outs``, ``metrics``, ``plots``)."""
    stages = yaml.safe_load(path.read_text(encoding="utf-8"))["stages"]
    outs = {n: _paths([*s.get("outs", ()), *s.get("metrics", ()), *s.get("plots", ())]) for n, s in stages.items()}

    def overlaps(dep: str, out: str) -> bool:
        return dep == out or dep.startswith(out.rstrip("/") + "/") or out.startswith(dep.rstrip("/") + "/")

    reads = {name: tuple(other for other in stages if other != name and any(
        overlaps(d, o) for d in _paths(spec.get("deps")) for o in outs[other])) for name, spec in stages.items()}
    return StageGraph(reads, {n: tuple(shlex.split(s["cmd"])) for n, s in stages.items()})


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
        self.graph = stage_graph()

    def add_shared(self) -> None:
        p, s = self.path, f"{SHARED}."
        corpora = list(dict.fromkeys((*self.base.data.train_corpora, self.base.slr.corpus)))
        if "synthetic" in corpora:
            self.steps.append(self.step(SHARED, "generate-corpus", p))
        for corpus in corpora:
            stage = "fit-corpus" if corpus == "synthetic" else f"fit-corpus-{corpus}"
            deps = (s + "generate-corpus",) if corpus == "synthetic" else ()
            self.steps.append(Step(SHARED, stage, p, _argv("fit_corpus", p, "--corpus", corpus), deps))
        self.fits = tuple(st.name for st in self.steps if st.stage.startswith("fit-corpus"))
        for stage in ("train-tokenizers", "tokenize", "train-backtranslation", "evaluate-backtranslation",
                      "train-backtranslation-skeleton"):
            self.steps.append(self.step(SHARED, stage, p))

    def step(self, variant: str, stage: str, path: Path, links: tuple[tuple[Path, Path], ...] = (),
             after: tuple[str, ...] = (), provider: Mapping[str, str] | None = None) -> Step:
        """``variant``'s step of ``stage``: it reads each stage ``dvc.yaml`` says it reads from the variant's own
        step when planned, else from ``provider[stage]`` or the shared steps (a stage nobody runs is not read)."""
        if stage not in self.graph.cmd:
            raise StudyError(f"stage {stage} is not in {DVC_YAML.name}; the study runs only dvc.yaml's stages")
        planned = {st.name for st in self.steps}
        deps: list[str] = []
        for read in self.graph.reads[stage]:
            if read == FIT:
                deps.extend(self.fits)
                continue
            name = next((f"{v}.{read}" for v in (variant, (provider or {}).get(read, SHARED))
                         if f"{v}.{read}" in planned), None)
            if name is not None:
                deps.append(name)
        argv = (*self.graph.cmd[stage], "--params", str(path))
        return Step(variant, stage, path, argv, tuple(dict.fromkeys(deps)), links, after)

    def add(self, name: str, settings: dict, stages: Sequence[str], shared_dirs: Sequence[str] = (),
            generated_from: str | None = None, after: Mapping[str, tuple[str, ...]] | None = None) -> None:
        """A variant's steps; its models folder links ``shared_dirs`` (DataConfig properties) of the shared models,
        its generated folder is that of the variant ``generated_from`` (whose generate-smlm it reads)."""
        path, params = self.writer.write(name, settings)
        links = tuple((getattr(params.data, d), getattr(self.shared.data, d)) for d in shared_dirs)
        provider = {}
        if generated_from is not None:
            source = _folders(self.root, generated_from)["data"]["generated_dir"]
            links += ((Path(params.data.generated_dir), Path(source)),)
            provider["generate-smlm"] = generated_from
        for stage in stages:
            self.steps.append(self.step(name, stage, path, links, (after or {}).get(stage, ()), provider))

    def add_tokenizers(self, seed: int) -> None:
        for quantizer, batch in TOKENIZER_SETTINGS:
            if (quantizer, batch, seed) != ("fsq", 16, self.shared_seed):  # that one is the shared run
                self.add(f"tokenizer-{quantizer}-b{batch}-s{seed}", {"tokenizer": {"quantizer": quantizer},
                         "tokenizer_train": {"batch_size": batch, "seed": seed}}, ["train-tokenizers"])

    def add_smlm(self, seed: int) -> None:
        # the objective's ablation at equal epochs (shared steps) and at equal production updates (added steps)
        for objective, steps, kind in ((True, "shared", "translation"), (False, "shared", "production"),
                                       (True, "added", "translation-added")):
            name = f"smlm-{kind}-s{seed}"
            self.add(name, {"smlm_train": {"translation_objective": objective, "translation_steps": steps,
                                           "seed": seed}},
                     ["train-smlm", "generate-smlm", "evaluate-smlm"], ("tokenizers_dir", "backtranslation_dir"))

    def add_slr(self, seed: int) -> None:
        self.add(f"slr-s{seed}", {"slr_train": {"seed": seed}}, ["train-slr", "evaluate-slr"], ("tokenizers_dir",))

    def add_sgsa(self, seed: int, infinite: bool) -> None:
        """N = inf (the SGSA system alone), or the configured N beside PT, judged with the same seed's SMLM."""
        dirs, stages = ("tokenizers_dir", "skeleton_judge_dir"), ["train-sgsa", "evaluate-sgsa"]
        if infinite:
            self.add(f"sgsa-ninf-s{seed}", {"sgsa": {"temporal_adjacency": 0},
                                            "sgsa_train": {"systems": ["sgsa"], "seed": seed}}, stages, dirs)
            return
        name, smlm = f"sgsa-n{self.base.sgsa.temporal_adjacency}-s{seed}", f"smlm-translation-s{seed}"
        inf = tuple(st.name for st in self.steps if st.variant.startswith("sgsa-ninf-") and st.stage == "evaluate-sgsa")
        self.add(name, {"sgsa_train": {"systems": ["pt", "sgsa"], "seed": seed}}, stages, dirs, generated_from=smlm,
                 after={"evaluate-sgsa": inf})


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

