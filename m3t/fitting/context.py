"""What every clip of a fit-corpus job needs, built once per worker process: the body model, its cache key, the
corpus adapter and the import settings (:class:`FitContext`, :func:`worker_context`).

A context is also what the tracker dispatch reads (:class:`m3t.trackers.dispatch.TrackingInputs`): the trackers'
settings, and the body model the simulated tracker projects ground-truth motion with.
"""
from __future__ import annotations

import threading

from m3t.body.factory import body_cache_key, load_body_model
from m3t.body.protocol import BodyModel
from m3t.corpora.base import CorpusAdapter, open_corpus
from m3t.fitting.config import FitJob
from m3t.fitting.imports import ImportSettings, import_settings
from m3t.trackers.config import MediaPipeConfig, SimulatedTrackerConfig


class FitContext:
    """What every clip of a job needs, built lazily and once per process: the body model, the corpus adapter,
    the import settings."""

    def __init__(self, job: FitJob, body: BodyModel | None = None):
        self.job = job
        self._body = body
        self._corpus: CorpusAdapter | None = None
        self._body_key: object | None = None
        self._import_settings: ImportSettings | None = None

    @property
    def body(self) -> BodyModel:
        if self._body is None:
            self._body = load_body_model(self.job.body)
        return self._body

    @property
    def body_key(self) -> object:
        if self._body_key is None:  # hashing licensed model files once per process, not once per clip
            self._body_key = body_cache_key(self.job.body)
        return self._body_key

    @property
    def corpus(self) -> CorpusAdapter:
        if self._corpus is None:
            self._corpus = open_corpus(self.job.corpus, self.job.source.root, **self.job.source.options)
        return self._corpus

    @property
    def mediapipe(self) -> MediaPipeConfig:
        return self.job.mediapipe

    @property
    def simulated(self) -> SimulatedTrackerConfig:
        return self.job.tracker

    @property
    def import_settings(self) -> ImportSettings:
        """What importing this job's clips depends on (reads SMPL-X's mean hand once per process if needed)."""
        if self._import_settings is None:
            self._import_settings = import_settings(self.job, self.corpus.config)
        return self._import_settings


_CONTEXTS: dict[str, FitContext] = {}
_CONTEXTS_LOCK = threading.Lock()


def worker_context(job: FitJob) -> FitContext:
    """This process' context for ``job`` (one body model per process and job, shared by its threads)."""
    key = job.key()
    with _CONTEXTS_LOCK:
        if key not in _CONTEXTS:
            _CONTEXTS.clear()  # one job at a time per process: drop the previous job's model
            _CONTEXTS[key] = FitContext(job)
        return _CONTEXTS[key]
