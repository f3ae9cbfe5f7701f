"""Configs of the fitting component (params.yaml ``fitting``, ``fusion``, ``fit_corpus``) and the job of one
corpus run. Configs only: the engine (:mod:`m3t.fitting.corpus`) and the refinement (:mod:`m3t.fitting.fit`)
import them, so reading params.yaml never imports the fitting code.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal

from m3t.body.config import BodyConfig
from m3t.corpora.base import CORPORA, CorpusSource
from m3t.digest import json_digest
from m3t.trackers.config import MediaPipeConfig, SimulatedTrackerConfig


@dataclass(frozen=True)
class FittingConfig:
    """params.yaml ``fitting``: M3T App. C, Eq. A.3, L = w_kp L_kp + w_acc L_acc + w_reg L_reg."""

    iterations: int = 100  # objective evaluations of the joint stage (lbfgs: at most; adam: steps)
    camera_iterations: int = 20  # of the camera-only stage
    lr: float = 0.02
    w_kp: float = 1.0
    w_acc: float = 0.5
    w_reg: float = 0.01
    fit_identity: bool = True
    focal_guess: float = 1.2  # focal length in units of max(width, height) when the track has no intrinsics
    camera_distance: float = 2.5  # initial camera distance in metres, in front of the chest
    device: str = "cpu"
    # lbfgs: L-BFGS per clip (one over a batch of fit_corpus.batch_clips, shared identity); lbfgs_batched: the
    # same algorithm for every clip of a batch (its own identity), one objective evaluation for all
    # (m3t.fitting.lbfgs); lbfgs_lockstep: a vectorised per-clip L-BFGS with backtracking, for GPU batches
    # (m3t.fitting.lockstep); adam: the first solver (it used 200 + 100 steps)
    solver: Literal["lbfgs", "adam", "lbfgs_batched", "lbfgs_lockstep"] = "lbfgs_batched"
    lbfgs_round: int = 25  # iterations between convergence tests
    lbfgs_history: int = 100
    tolerance: float = 1e-3  # stop once a round improved the loss by less than this (relative)

    @property
    def per_clip_problems(self) -> bool:
        """Whether every clip of a batch is its own problem (own identity) rather than one problem over the batch."""
        return self.solver in ("lbfgs_batched", "lbfgs_lockstep")


@dataclass(frozen=True)
class FusionConfig:
    use_external: bool = True  # fuse the NLF / WiLoR / Pixel3DMM outputs found beside a clip's media
    min_confidence: float = 0.3
    max_gap: int = 12  # frames; longer gaps hold the nearest covered value instead of interpolating


@dataclass(frozen=True)
class FitCorpusConfig:
    """params.yaml ``fit_corpus``: how a corpus run goes (where each corpus lives: ``corpora.<name>``)."""

    default_corpus: Literal[CORPORA] = "synthetic"  # the corpus of `--corpus` when none is named
    cache_dir: str = ".cache/fit"  # tracks and per-clip fits, content-addressed (shared by every corpus)
    workers: int = 2  # processes of the local executor (1 = in this process), or of the LocalCluster of dask
    max_clips: int = 0  # 0 = every clip
    # a signer's clips fitted together, at most this many (1 = one at a time): with lbfgs_batched each its own problem,
    # with lbfgs one problem with one identity
    batch_clips: int = 16
    batch_frames: int = 2048  # frames per fit at most; a batch's further chunks hold the identity of its first
    render_clips: int = 2  # fitted clips pictured in the MLflow run
    # where clips are fitted (m3t.fitting.cluster): local = `workers` processes here; dask = a Dask cluster, on
    # dask_address ("tcp://scheduler:8786") or, when it is "", a LocalCluster of `workers` processes for the run.
    # Every worker must see cache_dir and the corpus at the same paths. Shards do not depend on either key.
    executor: Literal["local", "dask"] = "local"
    dask_address: str = ""


@dataclass(frozen=True)
class FitJob:
    """Everything a worker needs for one corpus run: configs only (picklable), no built model."""

    corpus: str
    source: CorpusSource
    shards_dir: str
    run: FitCorpusConfig
    body: BodyConfig
    fitting: FittingConfig
    tracker: SimulatedTrackerConfig = field(default_factory=SimulatedTrackerConfig)
    mediapipe: MediaPipeConfig = field(default_factory=MediaPipeConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)

    def key(self) -> str:
        return json_digest(dataclasses.asdict(self), length=16)
