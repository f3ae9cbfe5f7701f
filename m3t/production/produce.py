"""``m3t produce``: one sentence -> signing, from the workspace's trained checkpoints and shards.

Systems (:data:`SYSTEMS`):

- ``smlm``: the Sign Motion Language Model (``models/smlm/smlm.pt``) generates motion tokens for the sentence
  (greedy, as generate-smlm), decoded to body-model parameters by the frozen tokenizers (``models/tokenizers``),
  posed with the body model's default identity. Words the model cannot read are the words whose text tokens
  include ``<unk>`` (pieces its text vocabulary never kept);
- ``retrieval``: the baseline of :mod:`m3t.production.retrieval` over the training shards: the nearest training
  clip's motion, unchanged, with its signer's identity. Words of the input its text lacks are listed;
- ``lexicon``: the baseline of :mod:`m3t.production.lexicon` over the training split's isolated signs: one stored
  sign per gloss of ``gloss`` when given (e.g. ``"BOOK CHILD READ"``), else per word of the text that names a
  sign, stitched with ``params.baselines.transition_frames`` interpolated frames, posed with the body model's
  default identity. Glosses / words without an entry are listed. With ``lexicon_dir`` (a folder in
  spoken-to-signed's ``lexicon.csv`` + ``.pose`` layout, :mod:`m3t.production.pose_lexicon`) the signs are the
  folder's ``.pose`` files stitched as points: ``<name>.pose`` (holistic) and ``<name>.npz`` (``points``) only,
  ``language`` being the lexicon's signed-language code (e.g. ``ase``), unknown words fingerspelled;
- ``pt`` / ``sgsa``: the skeletal systems of train-sgsa (``models/sgsa/<system>.pt``) decode the text with their
  own counter (as evaluate-sgsa does), back to metres at the shoulder width of the body model's default identity.
  They produce a skeleton, not parameters: ``<name>.pose`` holds the skeleton's joints, ``<name>.npz`` the
  ``points`` (T, J, 3) and the MP4 draws the skeleton. Words their text vocabulary lacks (``<unk>``) are listed.

Outputs in ``out`` under ``name`` (default: a slug of the sentence): ``<name>.pose`` (pose-format's MediaPipe
Holistic layout, :func:`m3t.render.posefile.export_pose`), ``<name>.npz`` (the parameters by modality, ``identity``
and ``fps``), ``<name>.mp4`` (the mesh; skipped with ``video=False``) and ``<name>.json`` (what was produced: system,
frames, fps, the words not handled, the retrieved clip). Each file is written whole or not at all. A missing
checkpoint or shard names the stage that writes it.

Axis legend: T frames, D_m a modality's width, P identity dimension.
"""
from __future__ import annotations

import re
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from m3t.atomic import atomic_path, write_json
from m3t.body.protocol import BodyModel
from m3t.config import Params
from m3t.production.retrieval import RetrievalIndex, normalise, words
from m3t.shards.io import read_split

SYSTEMS = ("smlm", "retrieval", "lexicon", "pt", "sgsa")
SKELETAL = ("pt", "sgsa")
DEFAULT_FPS = 25.0  # when the training shards record no rate for the language


class ProductionError(ValueError):
    """A sentence that cannot be produced; the message says why and what to do."""


@dataclass
class Production:
    """One produced sentence: parameters (T, D_m) by modality, the (P,) identity posing them, the rate."""

    system: str
    text: str
    language: str
    params: dict[str, np.ndarray]
    identity: np.ndarray
    fps: float
    unhandled_words: tuple[str, ...] = ()
    details: dict = field(default_factory=dict)
    files: dict[str, Path] = field(default_factory=dict)
    points: np.ndarray | None = None  # (T, J, 3): a skeletal system's (metres) or a .pose lexicon's output
    graph: object = None  # the SkeletonGraph of ``points``; None: holistic points in shoulder widths

    @property
    def frames(self) -> int:
        if self.points is not None:
            return len(self.points)
        return next((len(v) for v in self.params.values()), 0)

    def summary(self) -> dict:
        return {"system": self.system, "text": self.text, "language": self.language, "frames": self.frames,
                "fps": self.fps, "unhandled_words": list(self.unhandled_words), **self.details,
                "files": {k: p.name for k, p in self.files.items()}}


def slug(text: str, limit: int = 40) -> str:
    """A file name for a sentence: its normalised words joined by ``_``, at most ``limit`` characters."""
    name = re.sub(r"\s+", "_", normalise(text))[:limit].strip("_")
    return name or "produced"


def _language_fps(clips: Sequence, language: str) -> float:
    rates = Counter(c.clip.fps for c in clips if c.clip.language == language and c.clip.fps > 0)
    return float(rates.most_common(1)[0][0]) if rates else DEFAULT_FPS


def _train_clips(params: Params, modalities: Sequence[str] | None = None) -> list:
    try:
        return read_split(params.data.shards_dirs, "train", modalities)
    except FileNotFoundError as exc:
        raise ProductionError(str(exc)) from exc


def produce_smlm(text: str, language: str, params: Params, body: BodyModel) -> Production:
    from m3t.smlm.checkpoint import load_smlm
    from m3t.smlm.generate import generate_motion
    from m3t.smlm.vocab import VocabularyError
    from m3t.tokenizers.evaluate import decode_streams
    from m3t.tokenizers.tokenize import load_tokenizers

    data = params.data
    try:
        loaded = load_smlm(data.smlm_dir / "smlm.pt")
    except FileNotFoundError as exc:
        raise ProductionError(str(exc)) from exc
    if not (data.tokenizers_dir).is_dir():
        raise ProductionError(f"tokenizers {data.tokenizers_dir} not found; run `dvc repro train-tokenizers` first")
    tokenizers, _ = load_tokenizers(data.tokenizers_dir)
    vocab = loaded.vocab
    try:
        generated = generate_motion(loaded.model, vocab, [text], [language])[0]
    except VocabularyError as exc:
        raise ProductionError(str(exc)) from exc
    if not len(generated.tokens["body"]):
        raise ProductionError(f"the SMLM stopped at its first step for {text!r}: it produced no motion")
    unk = vocab.text.unk_id
    unhandled = tuple(w for w in dict.fromkeys(text.split()) if unk in vocab.text.encode(w))
    motion = decode_streams(tokenizers, generated.tokens)
    fps = _language_fps(_train_clips(params, modalities=()), language)
    return Production("smlm", text, language, motion, body.default_identity().detach().cpu().numpy(), fps,
                      unhandled, {"steps": len(generated.tokens["body"]), "stopped": generated.stopped})


def produce_retrieval(text: str, language: str, params: Params, body: BodyModel) -> Production:
    index = RetrievalIndex(_train_clips(params))
    try:
        found = index.nearest(text, language)
    except ValueError as exc:
        raise ProductionError(str(exc)) from exc
    clip = found.clip
    return Production("retrieval", text, language, dict(clip.params), np.asarray(clip.identity), clip.clip.fps or
                      DEFAULT_FPS, found.missing_words,
                      {"retrieved_clip": clip.clip.id, "retrieved_text": clip.clip.text, "match": found.match,
                       "chrf": found.score, "words": len(words(normalise(text), language))})


def produce_lexicon(text: str, language: str, params: Params, body: BodyModel, gloss: str | None = None) -> Production:
    from m3t.production.lexicon import Lexicon

    train = _train_clips(params)
    lexicon = Lexicon(train)
    if not len(lexicon):
        raise ProductionError(f"the training shards of {list(params.data.train_corpora)} hold no isolated sign with a "
                              "gloss: the lexicon baseline has no entry (use --system retrieval or smlm)")
    made = lexicon.lookup(text, gloss, language, "gloss" if gloss else "words", params.baselines.transition_frames)
    if not made.frames:
        raise ProductionError(f"no lexicon entry for any {made.input} of {gloss or text!r} (looked up: "
                              f"{' '.join(made.missing)}); the lexicon holds {', '.join(sorted(lexicon.entries))}")
    return Production("lexicon", text, language, made.params, body.default_identity().detach().cpu().numpy(),
                      _language_fps(train, language), tuple(dict.fromkeys(made.missing)),
                      {"input": made.input, "signs": " ".join(g for g, _ in made.used),
                       "entries": " ".join(cid for _, cid in made.used)})


def produce_skeletal(text: str, language: str, params: Params, body: BodyModel, system: str) -> Production:
    import torch

    from m3t.body.skeleton_points import normalise as normalise_points
    from m3t.sgsa.checkpoint import load_sgsa
    from m3t.sgsa.data import text_tokens
    from m3t.sgsa.evaluate import produced_points
    from m3t.shards.skeletons import graph_points

    path = params.data.sgsa_dir / f"{system}.pt"
    if not path.exists():
        raise ProductionError(f"{path} not found; run `dvc repro train-sgsa` (sgsa_train.systems must hold {system!r})")
    loaded = load_sgsa(path)
    tokens = text_tokens(text, language)[: loaded.model.cfg.max_text_tokens]
    vocab = loaded.text_vocab
    unk = vocab.stoi.get("<unk>")
    unhandled = tuple(dict.fromkeys(t for t in tokens[1:] if vocab.encode([t])[0] == unk))
    ids = torch.tensor([vocab.encode(tokens)], dtype=torch.long)
    loaded.model.eval()
    with torch.no_grad():
        frames = loaded.model.generate(ids, torch.ones_like(ids, dtype=torch.bool), loaded.model.cfg.max_frames)[0]
    identity = body.default_identity().detach().cpu().numpy()
    rest = {k: v.detach().cpu().numpy() for k, v in body.rest_params(1).items()}
    _, scale = normalise_points(graph_points(body, rest, identity, loaded.graph), loaded.graph)
    points = produced_points(frames.cpu().numpy(), loaded.graph, scale)
    fps = _language_fps(_train_clips(params, modalities=()), language)
    return Production(system, text, language, {}, identity, fps, unhandled,
                      {"skeleton": loaded.graph.name, "scale_m": float(scale)}, points=points, graph=loaded.graph)


def produce_pose_lexicon(text: str, language: str, params: Params, folder: str | Path) -> Production:
    from m3t.production.pose_lexicon import LexiconError, PoseLexicon

    try:
        made = PoseLexicon(folder).lookup(text, language, params.baselines.transition_frames, "installed")
    except (LexiconError, OSError) as exc:
        raise ProductionError(str(exc)) from exc
    return Production("lexicon", text, language, {}, np.zeros(0, np.float32), made.fps, tuple(made.missing),
                      {"lexicon": str(folder), "signs": " ".join(w for w, _ in made.used),
                       "fingerspelled": " ".join(made.fingerspelled)}, points=made.points)


def write_production(result: Production, body: BodyModel, out: str | Path, name: str, video: bool = True,
                     progress: bool = False) -> Production:
    """The files of the module doc, into ``out``; their paths in ``result.files``."""
    from m3t.render.posefile import export_pose

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if result.points is not None:
        return _write_skeleton(result, out, name, video, progress)
    result.files["pose"] = export_pose(out / f"{name}.pose", body, result.params, result.identity, result.fps)
    with atomic_path(out / f"{name}.npz") as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **result.params, identity=result.identity, fps=np.float64(result.fps))
    result.files["params"] = out / f"{name}.npz"
    if video:
        from m3t.render.mesh import clip_vertices
        from m3t.render.mesh_video import render_mesh_video

        result.files["video"] = render_mesh_video(
            {result.system: clip_vertices(body, result.params, result.identity)}, body.faces, out / f"{name}.mp4",
            fps=result.fps, title=f"{result.text} ({result.language})", progress=progress)
    result.files["summary"] = out / f"{name}.json"
    write_json(result.files["summary"], result.summary())
    return result


def _write_skeleton(result: Production, out: Path, name: str, video: bool, progress: bool) -> Production:
    from m3t.production.pose_lexicon import write_holistic_pose
    from m3t.render.posefile import export_skeleton_pose

    if result.graph is None:  # holistic points of a .pose lexicon: no skeleton graph, no video
        result.files["pose"] = write_holistic_pose(out / f"{name}.pose", result.points, result.fps)
        video = False
    else:
        result.files["pose"] = export_skeleton_pose(out / f"{name}.pose", result.points, result.graph, result.fps)
    with atomic_path(out / f"{name}.npz") as tmp, open(tmp, "wb") as fh:
        np.savez(fh, points=result.points, fps=np.float64(result.fps))
    result.files["points"] = out / f"{name}.npz"
    if video:
        from m3t.render.skeleton_video import render_skeleton_video

        result.files["video"] = render_skeleton_video({result.system: result.points}, result.graph, out / f"{name}.mp4",
                                                      fps=result.fps, title=f"{result.text} ({result.language})",
                                                      progress=progress)
    result.files["summary"] = out / f"{name}.json"
    write_json(result.files["summary"], result.summary())
    return result


def produce(text: str, language: str, params: Params, system: str = "smlm", out: str | Path | None = None,
            name: str | None = None, video: bool = True, body: BodyModel | None = None,
            progress: bool = False, gloss: str | None = None, lexicon_dir: str | Path | None = None) -> Production:
    """Produce ``text`` in sign language ``language`` with ``system`` from the workspace of ``params``; with
    ``out``, write the files of the module doc there (under ``name``, default :func:`slug` of the text);
    ``gloss``: the lexicon's input when given (the other systems read the text); ``lexicon_dir``: the lexicon
    system's spoken-to-signed folder instead of the training shards' isolated signs."""
    if lexicon_dir is not None and system != "lexicon":
        raise ProductionError(f"a lexicon folder is the lexicon system's input; --system is {system!r}")
    if system not in SYSTEMS:
        raise ProductionError(f"system {system!r} cannot produce from text here; choose one of {', '.join(SYSTEMS)}")
    if not isinstance(text, str) or not text.strip():
        raise ProductionError("empty text: give a sentence to produce")
    if body is None:
        from m3t.body.factory import load_body_model

        body = load_body_model(params.body)
    if system == "lexicon" and lexicon_dir is not None:
        result = produce_pose_lexicon(text, language, params, lexicon_dir)
    elif system == "lexicon":
        result = produce_lexicon(text, language, params, body, gloss)
    elif system in SKELETAL:
        result = produce_skeletal(text, language, params, body, system)
    else:
        result = (produce_smlm if system == "smlm" else produce_retrieval)(text, language, params, body)
    if out is not None:
        write_production(result, body, out, name or slug(text), video, progress)
    return result
