"""``m3t score``: anyone's output scored against references under the field's named definitions
(docs/scoring.md), with no model of this project needed.

Inputs (:func:`score`):

- **pose folders**: two folders of ``.pose`` files (MediaPipe Holistic, pose-format's layout; read by
  :mod:`m3t.scoring.poses`), searched recursively and paired by their path below the folder without the suffix
  (``dev/01April_2010_Thursday_heute-6704.pose`` is clip ``dev/01April_2010_Thursday_heute-6704``). Definitions
  ``pose_eval`` (every variant of :data:`m3t.metrics.pose_eval.VARIANTS`, the mean distance over clips) and
  ``slrtp`` (DTW-MJE, wrist path ratio, duration ratio over the 178 keypoints, pooled as the challenge pools;
  its 25 fps rule applies to each side's own rate);
- **SMPL-X parameter folders**: two folders of SMPL-X parameters in SOKE's layout (``.pkl`` / ``.npz`` per clip,
  or per-frame pickles in one folder per clip; :mod:`m3t.scoring.smplx_folders`), paired by path as ``.pose``
  files are, converted to SMPL-FX by the SOKE import: definitions ``m3t`` and ``soke_exact`` (needs body.model
  ``smplfx``);
- **parameter shards**: two Parquet shards of this project (:mod:`m3t.scoring.params`; the prediction may be a
  token shard such as generate-smlm's ``generated.parquet``, decoded by the workspace's tokenizers): definitions
  ``m3t`` and ``soke_exact`` on the workspace's body model, and the text definitions of the judge's
  back-translations;
- **text files**: two ``.txt`` files, one sentence per line, paired by line; or two ``.tsv`` files with a header
  holding ``id`` and ``text`` columns, paired by id. Definitions ``slt``, ``soke``, ``slrtp``
  (:func:`m3t.metrics.definitions.text_metrics`) in the ``language`` given.

**Nothing is dropped unseen.** A clip that cannot be scored (no counterpart on the other side, an unreadable file,
different frame rates or layouts on the two sides, a metric that refuses it) is listed with its reason in
:attr:`ScoreReport.unscored`, per definition, and every row of the table says how many clips it averages. A run
where no clip can be scored at all is an error.

Axis legend: T frames, J joints, D coordinates.
"""
from __future__ import annotations

import csv
import io
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from m3t.body.protocol import BodyModel
from m3t.metrics.definitions import TEXT_DEFINITIONS, text_metrics
from m3t.metrics.pose_eval import (
    FACE_MESH,
    FACE_REFINED,
    POSE_POINTS,
    VARIANTS,
    pose_eval_distance,
)
from m3t.metrics.slrtp import (
    SLRTPPairStatistics,
    slrtp_metrics_from_statistics,
    slrtp_pair_statistics,
)
from m3t.scoring.params import score_parameter_shards
from m3t.scoring.poses import PoseClip, ScoreInputError, read_pose_clip, slrtp_array
from m3t.scoring.report import ScoreReport, check_definitions, pairing
from m3t.scoring.smplx_folders import (
    PARAMETER_SUFFIXES,
    parameter_files,
    score_smplx_folders,
)

POSE_DEFINITIONS = ("pose_eval", "slrtp")
TEXT_SUFFIXES = (".txt", ".tsv")
_KIND_NAMES = {"pose": ".pose files (or nothing scorable)", "smplx": "SMPL-X parameter files"}


# ---- inputs ---------------------------------------------------------------------------------------------------
def pose_files(folder: Path) -> dict[str, Path]:
    """Clip id (path below ``folder`` without ``.pose``, ``/``-separated) -> file, for every ``.pose`` below it."""
    return {p.relative_to(folder).with_suffix("").as_posix(): p for p in sorted(folder.rglob("*.pose"))}


def _folder_kind(folder: Path) -> str:
    """``"pose"`` (``.pose`` files) or ``"smplx"`` (SMPL-X parameter files, :mod:`m3t.scoring.smplx_folders`), by
    the files' suffixes; a folder holding both is an error."""
    poses, params = next(folder.rglob("*.pose"), None), next(iter(parameter_files(folder)), None)
    if poses is not None and params is not None:
        raise ScoreInputError(f"{folder} holds both .pose files ({poses.relative_to(folder)}) and SMPL-X parameter "
                              f"files ({params.relative_to(folder)}); score each kind from a folder of its own")
    return "smplx" if params is not None else "pose"


def read_sentences(path: Path) -> dict[str, str]:
    """Clip id -> sentence of a ``.txt`` (id = line number from 1) or ``.tsv`` (``id`` and ``text`` columns) file."""
    text = path.read_text(encoding="utf-8")
    if path.suffix == ".txt":
        return {str(n): line for n, line in enumerate(text.splitlines(), start=1)}
    rows = list(csv.DictReader(io.StringIO(text), delimiter="\t", quoting=csv.QUOTE_NONE))
    header = list(rows[0]) if rows else text.partition("\n")[0].split("\t")
    if "id" not in header or "text" not in header:
        raise ScoreInputError(f"{path}: a .tsv of sentences needs a header with 'id' and 'text' columns; found "
                              f"{header}")
    out: dict[str, str] = {}
    for n, row in enumerate(rows, start=2):
        key = row["id"]
        if key in out:
            raise ScoreInputError(f"{path} line {n}: id {key!r} appears twice; ids must be unique")
        out[key] = row["text"] or ""
    return out


# ---- scoring --------------------------------------------------------------------------------------------------
def score(prediction: str | Path, reference: str | Path, definitions: Sequence[str] | None = None,
          language: str = "en", progress: Callable[[Iterable], Iterable] | None = None,
          any_fps: bool = False, body: BodyModel | Callable[[], BodyModel] | None = None,
          judge: str | Path | None = None, beam_size: int = 1, length_penalty: float = 1.0,
          tokenizers_dir: str | Path | None = None, smplx_path: str | Path | None = None,
          flat_hand_mean: bool = False) -> ScoreReport:
    """Score ``prediction`` against ``reference`` (two folders of ``.pose`` files, or two sentence files; see
    the module doc) under ``definitions`` (default: every one that applies to the inputs); ``any_fps``: see
    :func:`score_pose_folders`; ``body``: the body model of parameter shards, or a function that loads it (called
    only for shards); ``judge``, ``beam_size``, ``length_penalty``: back-translation checkpoints and their
    decoding for the text definitions of shards; ``tokenizers_dir``: the tokenizers that decode a token shard
    (what generate-smlm writes); ``smplx_path``, ``flat_hand_mean``: the SMPL-X file whose mean hand the hand poses
    of SMPL-X parameter folders are relative to, or that they are absolute (:func:`score_smplx_folders`)."""
    pred, ref = Path(prediction), Path(reference)
    for path in (pred, ref):
        if not path.exists():
            raise ScoreInputError(f"{path} does not exist")
    if pred.suffix == ref.suffix == ".parquet" and pred.is_file() and ref.is_file():
        if body is None:
            raise ScoreInputError(f"{pred} and {ref} are parameter shards: scoring them needs the body model they "
                                  "were fitted with (body.model in params.yaml)")
        model = body if hasattr(body, "layout") else body()  # a body model (itself callable), or its loader
        return score_parameter_shards(pred, ref, model, definitions, progress, None if judge is None else Path(judge),
                                      beam_size, length_penalty, None if tokenizers_dir is None else Path(tokenizers_dir))
    if pred.is_dir() and ref.is_dir():
        kinds = _folder_kind(pred), _folder_kind(ref)
        if "smplx" in kinds and kinds[0] != kinds[1]:
            raise ScoreInputError(f"{pred} holds {_KIND_NAMES[kinds[0]]}, {ref} holds {_KIND_NAMES[kinds[1]]}; "
                                  "score a prediction against references of the same kind")
        if kinds[0] == "smplx":
            if body is None:
                raise ScoreInputError(f"{pred} and {ref} hold SMPL-X parameter files: scoring them needs the SMPL-FX "
                                      "body model (body.model: smplfx in params.yaml)")
            return score_smplx_folders(pred, ref, body, definitions, progress, smplx_path, flat_hand_mean)
        return score_pose_folders(pred, ref, definitions, progress, any_fps)
    if pred.suffix in TEXT_SUFFIXES and ref.suffix in TEXT_SUFFIXES and pred.is_file() and ref.is_file():
        return score_sentences(pred, ref, language, definitions)
    raise ScoreInputError(f"cannot score {pred} against {ref}: give two folders of .pose files, two parameter "
                          f"shards (.parquet) or two sentence files ({' / '.join(TEXT_SUFFIXES)}), or two folders of "
                          f"SMPL-X parameter files ({' / '.join(PARAMETER_SUFFIXES)})")


def score_sentences(pred: Path, ref: Path, language: str, definitions: Sequence[str] | None = None) -> ScoreReport:
    """Text definitions over two sentence files (one reference per hypothesis)."""
    chosen = check_definitions(definitions, tuple(TEXT_DEFINITIONS), "text")
    if pred.suffix != ref.suffix:
        raise ScoreInputError(f"{pred} and {ref} differ in format; give two .txt or two .tsv files")
    report = ScoreReport("text", str(pred), str(ref))
    hyps, refs = read_sentences(pred), read_sentences(ref)
    ids = pairing(hyps, refs, report, "line" if pred.suffix == ".txt" else "id")
    for name in chosen:
        values = text_metrics([hyps[i] for i in ids], [refs[i] for i in ids], language, [name])
        report.metrics.update(values)
        report.definition_of.update(dict.fromkeys(values, name))
        report.clips_scored[name] = len(ids)
    report.notes.append(f"language: {language}")
    return report


def _pose_eval_clip(p: PoseClip, r: PoseClip) -> tuple[dict[str, float], bool]:
    """Every variant's distance of one pair, and whether some variant fell back to its default distance (the
    peer's warning; counted in the report's notes instead of printed per clip)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        values = {name: pose_eval_distance(p.points, r.points, name) for name in VARIANTS}
    return values, any(issubclass(w.category, RuntimeWarning) for w in caught)


def _slrtp_clip(p: PoseClip, r: PoseClip, where: str) -> SLRTPPairStatistics:
    a, b = slrtp_array(p.points), slrtp_array(r.points)
    present_a, present_b = ~np.isnan(a).any(-1), ~np.isnan(b).any(-1)  # slrtp's masks: True where present
    return slrtp_pair_statistics(a, b, present_a, present_b, p.fps, r.fps, where=where)


def _mismatch(p: PoseClip, r: PoseClip, any_rates: bool) -> str | None:
    if p.fps != r.fps and not any_rates:
        return (f"prediction at {p.fps:g} fps, reference at {r.fps:g} fps; resample the prediction to the "
                "reference's rate, or score across rates as the peers do (--any-fps)")
    if p.points.shape[2] != r.points.shape[2]:
        return (f"prediction has {p.points.shape[2]} coordinates per point, reference {r.points.shape[2]}; write "
                "both with the same dimensions")
    return None


def _common_face(p: PoseClip, r: PoseClip) -> tuple[PoseClip, PoseClip, bool]:
    """The pair on one face layout: a refined 478-point face loses its 10 iris points (mesh 468-477) when the
    other side has the 468-point mesh. Only ``pose_eval_dtw`` (every point) sees the difference; the hand and
    upper-body selections never held iris points."""
    if p.face_points == r.face_points:
        return p, r, False
    def mesh_only(c: PoseClip) -> PoseClip:
        if c.face_points != FACE_REFINED:
            return c
        keep = np.r_[0:len(POSE_POINTS) + FACE_MESH, len(POSE_POINTS) + FACE_REFINED:c.points.shape[1]]
        return replace(c, points=c.points[:, keep])

    return mesh_only(p), mesh_only(r), True


def score_pose_folders(pred: Path, ref: Path, definitions: Sequence[str] | None = None,
                       progress: Callable[[Iterable], Iterable] | None = None, any_fps: bool = False) -> ScoreReport:
    """Motion definitions over two folders of holistic ``.pose`` files. A pair at two frame rates is refused
    unless ``any_fps``: pose-evaluation's DTW ignores rates and the SLRTP rule halves each 25 fps side, so the
    peers score such pairs as they come."""
    chosen = check_definitions(definitions, POSE_DEFINITIONS, "pose")
    report = ScoreReport("pose", str(pred), str(ref))
    pred_files, ref_files = pose_files(pred), pose_files(ref)
    ids = pairing(pred_files, ref_files, report, ".pose file")
    pose_eval: dict[str, list[float]] = {name: [] for name in VARIANTS}
    slrtp: list[SLRTPPairStatistics] = []
    defaulted = irises_dropped = 0
    for clip in (progress or (lambda x: x))(ids):
        try:
            p, r = read_pose_clip(pred_files[clip], clip), read_pose_clip(ref_files[clip], clip)
        except ScoreInputError as exc:
            report.unscored.append({"clip": clip, "definition": "all", "reason": str(exc)})
            continue
        reason = _mismatch(p, r, any_fps)
        if reason:
            report.unscored.append({"clip": clip, "definition": "all", "reason": reason})
            continue
        p, r, reduced = _common_face(p, r)
        irises_dropped += reduced
        if "pose_eval" in chosen:
            try:
                values, fell_back = _pose_eval_clip(p, r)
            except ValueError as exc:
                report.unscored.append({"clip": clip, "definition": "pose_eval", "reason": str(exc)})
            else:
                for name, value in values.items():
                    pose_eval[name].append(value)
                    report.per_clip.append({"clip": clip, "definition": "pose_eval", "metric": name, "value": value})
                defaulted += fell_back
        if "slrtp" in chosen:
            try:
                stats = _slrtp_clip(p, r, clip)
            except ValueError as exc:
                report.unscored.append({"clip": clip, "definition": "slrtp", "reason": str(exc)})
            else:
                slrtp.append(stats)
                for name, value in slrtp_metrics_from_statistics([stats]).items():
                    if name in ("slrtp_dtw_mje", "slrtp_wrist_path_ratio", "slrtp_duration_ratio"):
                        report.per_clip.append({"clip": clip, "definition": "slrtp", "metric": name, "value": value})
    if "pose_eval" in chosen and pose_eval[next(iter(VARIANTS))]:
        for name, values in pose_eval.items():
            report.metrics[name] = float(np.mean(values))
            report.definition_of[name] = "pose_eval"
        report.clips_scored["pose_eval"] = len(pose_eval[next(iter(VARIANTS))])
        if defaulted:
            report.notes.append(f"pose_eval: {defaulted} clip(s) had a non-finite distance in some variant and "
                                "count with that variant's default distance (the peer's fallback)")
    if irises_dropped:
        report.notes.append(f"{irises_dropped} pair(s) had a 478-point face on one side and 468 on the other: "
                            "scored on the 468 mesh points (the 10 iris points left out)")
    if "slrtp" in chosen and slrtp:
        values = slrtp_metrics_from_statistics(slrtp)
        for name in ("slrtp_dtw_mje", "slrtp_wrist_path_ratio", "slrtp_duration_ratio"):
            report.metrics[name] = values[name]
            report.definition_of[name] = "slrtp"
        report.clips_scored["slrtp"] = len(slrtp)
    if not report.metrics:
        reasons = "; ".join(f"{u['clip']}: {u['reason']}" for u in report.unscored[:3])
        raise ScoreInputError(f"no clip could be scored ({len(report.unscored)} refused; {reasons})")
    report.notes.append("pose units: the files' own coordinates (pose-format holistic: pixels)")
    return report

