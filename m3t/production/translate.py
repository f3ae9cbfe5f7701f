"""``m3t translate``: one signing input -> text, with the workspace's trained SMLM (and its judge).

Input kinds, by path:

- a **video file** (``.mp4``, ``.avi``, ``.mov``, ``.mkv``, ``.webm``) or a **frame folder**: MediaPipe Holistic
  tracks it offline (:func:`m3t.trackers.mediapipe_holistic.track_media`, params.yaml ``mediapipe``);
- a **.pose file** (MediaPipe Holistic, as pose-format writes it): its landmarks are the track
  (:func:`m3t.trackers.posefile.load_pose_track`);
- a **parameter file** (``.npz``, as ``m3t produce`` writes it: one (T, D_m) array per modality of the workspace's
  body model, optional ``identity``): no tracking or fitting.

Then: fitting of the body model to the track (params.yaml ``fitting``, from the rest pose as fit-corpus does without
external trackers) -> motion tokens by the frozen tokenizers -> the SMLM's translation (greedy, its ``TXT``
prompt) and, when the workspace has a judge for the language, the judge's back-translation of the fitted motion.
Every step's wall time is reported.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from m3t.body.protocol import BodyModel
from m3t.config import Params
from m3t.production.produce import ProductionError

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm")


@dataclass
class Translation:
    """What :func:`translate` found: the SMLM's sentence, the judge's (None without a judge), the fitted motion's
    frame count and each step's seconds."""

    input: str
    kind: str  # "video", "frames", "pose" or "parameters"
    language: str
    smlm: str
    judge: str | None
    frames: int
    seconds: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


def input_kind(path: Path) -> str:
    """``"video"``, ``"frames"``, ``"pose"`` or ``"parameters"``; :class:`ProductionError` for anything else."""
    if path.is_dir():
        return "frames"
    if not path.is_file():
        raise ProductionError(f"{path} does not exist")
    suffix = path.suffix.lower()
    if suffix in VIDEO_SUFFIXES:
        return "video"
    if suffix == ".pose":
        return "pose"
    if suffix == ".npz":
        return "parameters"
    raise ProductionError(f"{path}: cannot translate a {suffix or 'suffix-less'} file; give a video "
                          f"({', '.join(VIDEO_SUFFIXES)}), a frame folder, a .pose file or a .npz of parameters")


def _parameters(path: Path, body: BodyModel) -> tuple[dict[str, np.ndarray], np.ndarray]:
    with np.load(path, allow_pickle=False) as arrays:
        dims = dict(body.layout.dims)
        missing = [m for m in dims if m not in arrays.files]
        if missing:
            raise ProductionError(f"{path}: no arrays {missing} of body model {body.name!r} (found {arrays.files}); "
                                  "write one (T, D) array per modality, as m3t produce does")
        params = {m: np.asarray(arrays[m], dtype=np.float32) for m in dims}
        identity = (np.asarray(arrays["identity"], dtype=np.float32) if "identity" in arrays.files
                    else body.default_identity().detach().cpu().numpy())
    frames = {len(v) for v in params.values()}
    bad = {m: v.shape for m, v in params.items() if v.ndim != 2 or v.shape[1] != dims[m]}
    if bad or len(frames) != 1 or frames == {0}:
        raise ProductionError(f"{path}: parameters {bad or {m: v.shape for m, v in params.items()}}; expected "
                              f"(T > 0, D) per modality with one T, D = {dims}")
    return params, identity


def _track(path: Path, kind: str, params: Params, progress: bool):
    if kind == "pose":
        from m3t.trackers.posefile import PoseFileError, load_pose_track

        try:
            return load_pose_track(path).track
        except PoseFileError as exc:
            raise ProductionError(str(exc)) from exc
    from m3t.trackers.media import MediaError
    from m3t.trackers.mediapipe_holistic import track_media

    try:
        return track_media(path, params.mediapipe, progress=progress)
    except (MediaError, ModuleNotFoundError) as exc:
        raise ProductionError(str(exc)) from exc


def translate_input(path: str | Path, language: str, params: Params, body: BodyModel | None = None,
                    judge: bool = True, progress: bool = False,
                    clock: Callable[[], float] = time.perf_counter) -> Translation:
    """Translate the signing in ``path`` (see the module doc) in sign language ``language``."""
    from m3t.corpora.clip import Clip
    from m3t.fitting.fit import fit_track
    from m3t.shards.schema import FittedClip
    from m3t.smlm.checkpoint import load_smlm
    from m3t.smlm.generate import translate
    from m3t.smlm.vocab import MOTION_STREAMS, VocabularyError
    from m3t.tokenizers.tokenize import load_tokenizers, tokenize_clip

    path = Path(path)
    kind = input_kind(path)
    data = params.data
    try:  # the checkpoints first: a missing one is reported before minutes of tracking and fitting
        loaded = load_smlm(data.smlm_dir / "smlm.pt")
    except FileNotFoundError as exc:
        raise ProductionError(str(exc)) from exc
    try:
        loaded.vocab.check_language(language)
    except VocabularyError as exc:
        raise ProductionError(str(exc)) from exc
    if not data.tokenizers_dir.is_dir():
        raise ProductionError(f"tokenizers {data.tokenizers_dir} not found; run `dvc repro train-tokenizers` first")
    if body is None:
        from m3t.body.factory import load_body_model

        body = load_body_model(params.body)
    seconds: dict[str, float] = {}
    start = clock()
    if kind == "parameters":
        motion, identity = _parameters(path, body)
        fps = 25.0
    else:
        track = _track(path, kind, params, progress)
        seconds["tracking"] = clock() - start
        start = clock()
        try:
            fitted = fit_track(track, body, params.fitting)
        except ValueError as exc:  # e.g. no landmark seen in any frame: no signer in the input
            raise ProductionError(f"{path}: cannot fit the body model to its track ({exc}); is a signer visible?") \
                from exc
        motion, identity, fps = fitted.params, fitted.identity, track.fps
        seconds["fitting"] = clock() - start
    start = clock()
    tokenizers, _ = load_tokenizers(data.tokenizers_dir)
    frames = len(next(iter(motion.values())))
    clip = Clip(path.stem, "input", "test", language, "", "", "", str(path), float(fps or 25.0))
    tokens = tokenize_clip(tokenizers, FittedClip(clip, "", motion, identity, {}, {}, body.name)).tokens
    seconds["tokens"] = clock() - start
    start = clock()
    codes = np.stack([tokens[s] for s in MOTION_STREAMS], axis=1)
    limit = loaded.model.cfg.max_motion_tokens
    notes = []
    if len(codes) > limit:
        notes.append(f"{len(codes)} motion tokens cut to the model's {limit}")
        codes = codes[:limit]
    if not len(codes):
        raise ProductionError(f"{path}: {frames} frames make no motion token; the input is too short")
    sentence = translate(loaded.model, loaded.vocab, [codes], [language])[0]
    seconds["smlm"] = clock() - start
    judged = None
    if judge:
        start = clock()
        judged = _judge(data.backtranslation_dir, language, motion, params, notes)
        if judged is not None:
            seconds["judge"] = clock() - start
    return Translation(str(path), kind, language, sentence, judged, frames, seconds, notes)


def _judge(folder: Path, language: str, motion: dict[str, np.ndarray], params: Params, notes: list[str]) -> str | None:
    from m3t.backtranslation.decode import translate as judge_translate
    from m3t.backtranslation.pipeline import load_models

    if not folder.is_dir() or not any(folder.glob("*.pt")):
        notes.append(f"no judge: {folder} holds no back-translation checkpoint (dvc repro train-backtranslation)")
        return None
    models = load_models(folder)
    if language not in models:
        notes.append(f"no judge for {language!r} (judges: {sorted(models)})")
        return None
    loaded = models[language]
    features = loaded.spec.features(motion, "input")
    cfg = params.backtranslation
    return judge_translate(loaded.model, loaded.text_vocab, loaded.processor, [features], cfg.beam_size,
                           cfg.length_penalty, 1)[0]
