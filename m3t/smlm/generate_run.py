"""generate-smlm's run, on the checkpoint train-smlm selected.

- :func:`run_generate`: every clip of ``smlm_generate.split``: text -> motion tokens (greedy, KV cache) and
  ground-truth motion tokens -> text; writes ``generated.parquet``, ``translations.jsonl``,
  ``pose/<clip>.pose`` and, for the first ``smlm_generate.render_clips`` clips, ``renders/<clip>.mp4`` (the
  body surface, reference / generated side by side) and ``renders/<clip>_skeleton.mp4`` (their skeletons and
  face points overlaid) into ``data.generated``. With ``fit_corpus.executor: dask`` the decoding (text -> motion,
  motion -> text) runs on fit-corpus's Dask cluster, a batch per task.
"""
from __future__ import annotations

from dataclasses import dataclass

from m3t.atomic import write_jsonl
from m3t.body.factory import BodyConfig, load_body_model
from m3t.body.protocol import BodyModel
from m3t.fitting.cluster import stage_executor
from m3t.fitting.config import FitCorpusConfig
from m3t.metrics.motion import MotionMetricsConfig
from m3t.shards.folders import DataConfig
from m3t.shards.tokens import (
    TokenClip,
    TokenInfo,
    write_token_shard,
)
from m3t.smlm.checkpoint import LoadedSMLM, load_smlm
from m3t.smlm.config import GenerateConfig
from m3t.smlm.evaluate import SMLMEvaluator
from m3t.smlm.pipeline import load_tokens, references, split_examples
from m3t.tokenizers.tokenize import load_tokenizers


@dataclass
class GenerationSetup:
    loaded: LoadedSMLM  # the checkpoint: model, vocabulary, training settings
    evaluator: SMLMEvaluator  # the split's clips, their references and the frozen tokenizers
    info: TokenInfo  # the tokenizers' streams, codebook sizes and downsampling
    skipped: list[dict]  # clips of the split the vocabulary cannot take (no language prompt, no text), with reasons
    cut: list[dict]  # clips over the model's text / motion limits: kept, cut to them, scored against the whole reference


def evaluator_for(cfg: GenerateConfig, data: DataConfig, body: BodyModel, device: str = "cpu") -> GenerationSetup:
    loaded = load_smlm(data.smlm_dir / "smlm.pt", device)
    tokenizers, info = load_tokenizers(data.tokenizers_dir)
    skipped: list[dict] = []
    cut: list[dict] = []
    examples = split_examples(load_tokens(data, cfg.split), loaded.vocab, loaded.model.cfg, skipped, cut)
    evaluator = SMLMEvaluator(body, tokenizers, loaded.vocab, examples, references(data, cfg.split),
                              batch_size=cfg.batch_size, motion=MotionMetricsConfig(mode=cfg.motion_metric))
    return GenerationSetup(loaded, evaluator, info, skipped, cut)


def run_generate(cfg: GenerateConfig, data: DataConfig, body: BodyModel, progress: bool = True,
                 cluster: FitCorpusConfig | None = None) -> dict[str, float]:
    """``cluster`` (params ``fit_corpus``) with ``executor: dask``: the decoding batches run on that cluster, whose
    workers load the checkpoint from the same path; the outputs are the same."""
    from tqdm.auto import tqdm

    from m3t.render.mesh import clip_vertices
    from m3t.render.mesh_video import render_mesh_video
    from m3t.render.posefile import export_pose
    from m3t.render.reconstruction import render_reconstruction

    setup = evaluator_for(cfg, data, body)
    loaded, evaluator, info, skipped = setup.loaded, setup.evaluator, setup.info, setup.skipped + setup.cut
    out = data.generated
    out.mkdir(parents=True, exist_ok=True)
    checkpoint = data.smlm_dir / "smlm.pt"
    with stage_executor(cluster) as executor:
        generated = evaluator.generate(loaded.model, progress, executor, checkpoint)
        translations = evaluator.translate(loaded.model, progress, executor, checkpoint)
    clips = []
    for example in evaluator.examples:
        g = generated[example.clip_id]
        steps = len(g.tokens["body"])
        clips.append(TokenClip(evaluator.references[example.clip_id].clip, steps * info.downsample,
                               {s: g.tokens[s] for s in info.streams}))
    write_token_shard(out / "generated.parquet", clips, info)
    write_jsonl(out / "translations.jsonl", ({"clip_id": e.clip_id, "language": e.language, "reference": e.text,
                                             "hypothesis": translations[e.clip_id]} for e in evaluator.examples))
    write_jsonl(out / "skipped.jsonl", skipped)
    rendered = 0
    for example in tqdm(evaluator.examples, desc="generate-smlm: export", disable=not progress):
        g, ref = generated[example.clip_id], evaluator.references[example.clip_id]
        if not g.tokens["body"].size:
            continue
        params = evaluator.motion_params(g)
        if cfg.export_pose:
            export_pose(out / "pose" / f"{example.clip_id}.pose", body, params, ref.identity, ref.clip.fps)
        if rendered < cfg.render_clips:
            title = f"{example.clip_id} ({example.language})"
            render_mesh_video({"reference": clip_vertices(body, ref.params, ref.identity),
                               "generated": clip_vertices(body, params, ref.identity)}, body.faces,
                              out / "renders" / f"{example.clip_id}.mp4", fps=ref.clip.fps or 25.0, title=title,
                              progress=progress)
            render_reconstruction(body, ref, params, out / "renders" / f"{example.clip_id}_skeleton.mp4",
                                  title=title, labels=("fitted", "generated"), progress=progress)
            rendered += 1
    return {"clips": float(len(clips)), "skipped": float(len(skipped)),
            "stopped_rate": float(sum(generated[e.clip_id].stopped for e in evaluator.examples) / max(len(clips), 1))}


def generate(cfg: GenerateConfig, data: DataConfig, body_cfg: BodyConfig, progress: bool = True,
             cluster: FitCorpusConfig | None = None) -> dict[str, float]:
    return run_generate(cfg, data, load_body_model(body_cfg), progress, cluster)


