"""Folders of SMPL-X parameters in SOKE's layout scored as the SMLM's evaluation scores them: each clip is converted
to SMPL-FX by the SOKE import (:func:`m3t.fitting.imports.import_clip`) and scored under definitions ``m3t`` and
``soke_exact`` by :func:`m3t.scoring.params.score_motion_pairs`, as two parameter shards are.

What a folder may hold (searched recursively; a clip's id is its path below the folder without the suffix, as for
``.pose`` files):

- **one file per clip** (``<clip>.pkl``, read with the allow-list unpickler, numpy arrays only; or ``<clip>.npz``):
  a dict of SOKE's frame records stacked over time, the arrays SOKE's loaders concatenate per frame
  (2000ZRL/SOKE ``mGPT/data/humanml/load_data.py``, ``keys``): ``smplx_root_pose`` (T, 3), ``smplx_body_pose``
  (T, 63), ``smplx_lhand_pose`` (T, 45), ``smplx_rhand_pose`` (T, 45), ``smplx_jaw_pose`` (T, 3), ``smplx_shape``
  (T, 10) or (10,), ``smplx_expr`` (T, 10); the smplx package's names (``global_orient``, ``body_pose``, ...,
  ``betas``, ``expression``) are read too. Other keys (a ``text``, an ``fps``) are ignored;
- **one folder per clip** of per-frame pickles, SOKE's released poses as its loaders read them
  (:func:`m3t.corpora.soke_smplx.load_smplx_sequence`: ``<clip>/<n>.pkl``, ``images<n>.pkl``,
  ``<clip>_<n>_3D.pkl``, one (D,) record per frame); the clip's id is the folder's path. A folder is read so when
  its first pickle holds one frame's (D,) vectors and every pickle in it is named by a frame number.

Not read: SOKE's test output (``test.py`` with ``TEST.SAVE_PREDICTIONS``, ``mGPT/models/base.py``
``test_step``: ``<split>_rank_<r>/<clip>.pkl`` holding ``feats_rst``, ``feats_ref`` (T, 133) and ``text``). Its
features are normalised by the training set's mean and std (``DATASET.H2S.MEAN_PATH`` / ``STD_PATH``) and lack the
root, the lower body and the shape; such a file is listed as unscored with that reason. De-normalise with SOKE's
``mean.pt`` / ``std.pt`` and write the SMPL-X arrays above (the 36 leading zeros of ``feats2joints``, the rest in
order: ``body_pose[33:]``, left hand, right hand, jaw, expression).

Conventions: hand poses are relative to SMPL-X's mean hand unless ``flat_hand_mean`` (SMPLer-X and SOKE build
SMPL-X with the smplx default ``flat_hand_mean=False``), so the mean hand is read from the SMPL-X file
(``body.smplx_path``). **Identity**: the reference's ``smplx_shape`` / ``betas`` (first 10, mean over frames) as
SMPL-X betas, FLAME shape 0, posing both sides (the scorer's rule); a per-clip file without a shape key gets the
neutral shape (zeros). SOKE's own evaluation poses both sides with one fixed shape instead; with one identity on
both sides the joint errors differ only through the bone lengths. The files carry no frame rate; the DTW metrics
align the two sequences whatever their rates, so pairs are scored as they come. What the import drops (global
orient, spine and legs, translation, eye rotations: SMPL-FX has no parameter for them, SOKE's evaluation zeroes
the same joints) is said in :mod:`m3t.fitting.imports`.

Axis legend: T frames, D values per frame.
"""
from __future__ import annotations

import zipfile
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import numpy as np

from m3t.body.protocol import BodyModel
from m3t.corpora.annotation_files import load_data_pickle
from m3t.corpora.clip import Clip
from m3t.corpora.listing import CorpusError
from m3t.corpora.soke_smplx import (
    SMPLX_DIMS,
    SMPLX_OPTIONAL,
    SOKE_NAMES,
    frame_number,
    load_smplx_sequence,
    stack_smplx_frames,
)
from m3t.declared import DeclaredSizeError
from m3t.fitting.imports import ImportSettings, import_clip, smplx_hand_mean
from m3t.metrics.scorer import MotionPair
from m3t.scoring.params import MOTION_DEFINITIONS, score_motion_pairs
from m3t.scoring.poses import ScoreInputError
from m3t.scoring.report import ScoreReport, check_definitions, pairing
from m3t.trackers.dispatch import ClipRefused

PARAMETER_SUFFIXES = (".pkl", ".npz")
SHAPE_KEYS = ("smplx_shape", "betas")  # per clip, (D,) allowed: one identity for the whole clip
SOKE_TEST_OUTPUT = "feats_rst"  # the key of SOKE's test-output pickles (normalised features, not SMPL-X arrays)
GROUP = "smplx/unknown"  # the files say neither corpus nor language


def parameter_files(folder: Path) -> list[Path]:
    """Every ``.pkl`` / ``.npz`` file below ``folder``."""
    return sorted(p for p in folder.rglob("*") if p.suffix in PARAMETER_SUFFIXES and p.is_file())


def smplx_clips(folder: Path) -> dict[str, Path]:
    """Clip id -> per-clip file or per-frame clip folder, for every clip below ``folder`` (see the module doc)."""
    clips: dict[str, Path] = {}
    frame_folders: set[Path] = set()
    for path in parameter_files(folder):
        parent = path.parent
        if parent in frame_folders:
            continue
        if parent != folder and _is_frame_folder(parent):
            frame_folders.add(parent)
            clips[parent.relative_to(folder).as_posix()] = parent
        else:
            clips[path.relative_to(folder).with_suffix("").as_posix()] = path
    return clips


def _is_frame_folder(folder: Path) -> bool:
    """Whether ``folder`` holds one clip's per-frame pickles: all named by frame number, the first one frame."""
    pickles = sorted(p for p in folder.iterdir() if p.suffix == ".pkl")
    if not pickles or any(p.suffix == ".npz" for p in folder.iterdir()):
        return False
    if any(frame_number(p.stem) is None for p in pickles):
        return False
    try:
        record = load_data_pickle(pickles[0], allow_numpy=True)
    except CorpusError:
        return False
    body = record.get("smplx_body_pose", record.get("body_pose")) if isinstance(record, dict) else None
    return body is not None and np.asarray(body).size == SMPLX_DIMS["body_pose"]


def _file_arrays(path: Path) -> dict:
    if path.suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as data:
                return {k: data[k] for k in data.files}
        except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
            raise ScoreInputError(f"{path}: not a readable .npz of arrays ({exc})") from exc
    try:
        raw = load_data_pickle(path, allow_numpy=True)
    except (CorpusError, DeclaredSizeError) as exc:
        raise ScoreInputError(str(exc)) from exc
    if not isinstance(raw, dict):
        raise ScoreInputError(f"{path}: expected a dict of SMPL-X arrays, found {type(raw).__name__}")
    return raw


def read_clip_file(path: Path) -> dict[str, np.ndarray]:
    """One per-clip file -> (T, D) float32 arrays under the smplx package's names (the adapter's checks, frame by
    frame); :class:`ScoreInputError` naming the file, the key and the shape when it cannot be read."""
    raw = _file_arrays(path)
    if SOKE_TEST_OUTPUT in raw:
        raise ScoreInputError(f"{path}: SOKE's test output ({SOKE_TEST_OUTPUT} / feats_ref: features normalised by "
                              "its training mean and std), not SMPL-X arrays; de-normalise them with SOKE's "
                              "mean.pt / std.pt and write the SMPL-X arrays (docs/scoring.md)")
    known = {*SOKE_NAMES, *SMPLX_DIMS, *SMPLX_OPTIONAL}
    arrays = {k: np.asarray(v) for k, v in raw.items() if k in known}
    shape_keys = [k for k in SHAPE_KEYS if k in arrays]
    timed = {k: v for k, v in arrays.items() if k not in shape_keys or v.ndim != 1}
    wrong = {k: v.shape for k, v in timed.items() if v.ndim != 2}
    if wrong:
        key = min(wrong)
        raise ScoreInputError(f"{path}: key {key!r} has shape {wrong[key]}; expected (T, D), one row per frame "
                              "(a clip's shape may be (D,))")
    frames = {v.shape[0] for v in timed.values()}
    if len(frames) > 1:
        raise ScoreInputError(f"{path}: keys differ in frame count ({ {k: v.shape[0] for k, v in timed.items()} }); "
                              "expected one T")
    count = frames.pop() if frames else 0
    if count == 0:
        raise ScoreInputError(f"{path}: no frames")
    constant = {k: arrays[k] for k in shape_keys if arrays[k].ndim == 1}
    if not shape_keys:  # no identity in the file: the neutral shape
        constant = {"smplx_shape" if any(k in SOKE_NAMES for k in arrays) else "betas": np.zeros(10, np.float32)}
    records = ((path, {**{k: v[t] for k, v in timed.items()}, **constant}) for t in range(count))
    try:
        return stack_smplx_frames(records)
    except CorpusError as exc:
        raise ScoreInputError(str(exc)) from exc
    except (ValueError, TypeError) as exc:  # values that are not numbers
        raise ScoreInputError(f"{path}: SMPL-X values that are not numbers ({exc})") from exc


def read_clip(path: Path) -> dict[str, np.ndarray]:
    """A per-clip file or a per-frame clip folder -> (T, D) arrays under the smplx package's names."""
    if path.is_dir():
        try:
            return load_smplx_sequence(path)
        except (CorpusError, DeclaredSizeError) as exc:
            raise ScoreInputError(str(exc)) from exc
        except (ValueError, TypeError) as exc:  # values that are not numbers
            raise ScoreInputError(f"{path}: SMPL-X values that are not numbers ({exc})") from exc
    return read_clip_file(path)


def _smplfx_body(body: BodyModel | Callable[[], BodyModel]) -> BodyModel:
    try:
        model = body if hasattr(body, "layout") else body()  # a body model (itself callable), or its loader
    except FileNotFoundError as exc:  # SMPLFXFilesMissing names each licensed file and its params.yaml key
        raise ScoreInputError(f"SMPL-X parameters are scored on SMPL-FX (body.model: smplfx in params.yaml); {exc}")\
            from exc
    if model.name != "smplfx":
        raise ScoreInputError(f"SMPL-X parameters are scored on SMPL-FX; the workspace's body model is "
                              f"{model.name!r}: set body.model: smplfx in params.yaml (it needs the licensed SMPL-X "
                              "and FLAME files of the body section)")
    return model


def _settings(model: BodyModel, smplx_path: str | Path | None, flat_hand_mean: bool) -> ImportSettings:
    flame_shape_dims = len(model.layout.identity_labels) - 10
    if flat_hand_mean:
        return ImportSettings("smplfx", flame_shape_dims)
    if smplx_path is None:
        raise ScoreInputError("SOKE-layout hand poses are relative to SMPL-X's mean hand (SMPLer-X and SOKE build "
                              "SMPL-X with flat_hand_mean=False); scoring them needs the SMPL-X file "
                              "(body.smplx_path in params.yaml) for its hands_meanl / hands_meanr")
    try:
        return ImportSettings("smplfx", flame_shape_dims, smplx_hand_mean(smplx_path))
    except ValueError as exc:  # ModelFileError: the file and the keys
        raise ScoreInputError(str(exc)) from exc


def _smplfx_clip(clip_id: str, source: dict[str, np.ndarray], settings: ImportSettings):
    clip = Clip(id=clip_id, corpus="smplx", split="test", language="unknown", signer="unknown",
                text="", gloss="", media=clip_id, fps=0.0)
    fitted, _ = import_clip(clip, "smplx_params", source, "", settings)
    return fitted.params, fitted.identity


def score_smplx_folders(pred: Path, ref: Path, body: BodyModel | Callable[[], BodyModel],
                        definitions: Sequence[str] | None = None,
                        progress: Callable[[Iterable], Iterable] | None = None,
                        smplx_path: str | Path | None = None, flat_hand_mean: bool = False) -> ScoreReport:
    """Score the SMPL-X clips below ``pred`` against those below ``ref`` on SMPL-FX (``body``: the model or its
    loader; ``smplx_path``: the SMPL-X file whose mean hand the hand poses are relative to, unused when
    ``flat_hand_mean``) under ``definitions`` (default ``m3t`` and ``soke_exact``). Unpaired, unreadable,
    wrong-shaped and frameless clips are listed in ``report.unscored`` with their reason."""
    chosen = check_definitions(definitions, MOTION_DEFINITIONS, "SMPL-X parameter")
    model = _smplfx_body(body)
    settings = _settings(model, smplx_path, flat_hand_mean)
    report = ScoreReport("parameters", str(pred), str(ref))
    pred_clips, ref_clips = smplx_clips(pred), smplx_clips(ref)
    ids = pairing(pred_clips, ref_clips, report, "SMPL-X clip")
    pairs = []
    for clip in (progress or (lambda x: x))(ids):
        try:
            p_params, _ = _smplfx_clip(clip, read_clip(pred_clips[clip]), settings)
            r_params, identity = _smplfx_clip(clip, read_clip(ref_clips[clip]), settings)
        except (ScoreInputError, ClipRefused) as exc:
            report.unscored.append({"clip": clip, "definition": "all", "reason": str(exc)})
            continue
        pairs.append(MotionPair(clip, GROUP, p_params, identity, r_params))
    if not pairs:
        raise ScoreInputError(f"no clip could be scored ({len(report.unscored)} refused; "
                              + "; ".join(f"{u['clip']}: {u['reason']}" for u in report.unscored[:3]) + ")")
    score_motion_pairs(report, pairs, model, chosen)
    hands = "absolute (flat_hand_mean)" if flat_hand_mean else "relative to SMPL-X's mean hand"
    report.notes.append(f"body model: smplfx (SMPL-X parameters imported as SOKE's are; hand poses {hands}); both "
                        "sides posed with the reference's betas; metres")
    return report
