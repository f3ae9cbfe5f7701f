"""Tokenise / reconstruct whole clips and measure a tokenizer: vertex errors through the body model and
codebook statistics.

:class:`ReconstructionProbe` holds validation clips (the first ``max_frames`` frames' worth, or all of them
with ``max_frames = 0``) and, per stream, the vertex region that stream moves
(:mod:`m3t.metrics.vertices`); :meth:`ReconstructionProbe.measure` reconstructs each stream of each clip
with the tokenizer (other streams kept), runs the body model and returns VPE / PA-VPE in mm plus the
parameter L2 error. Checkpoints are selected on ``vpe_mm`` (vertex error, App. 0.D.1).

Axis legend: T frames, D stream dim, N tokens, P identity dim.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from m3t.body.protocol import BodyModel, as_tensors
from m3t.metrics.vertices import (
    region_keypoints,
    region_vertices,
    stream_vertex_region,
    vertex_errors_mm,
)
from m3t.shards.schema import FittedClip
from m3t.tokenizers.data import (
    GROUPS,
    STREAMS,
    from_canonical,
    pad_to_multiple,
    to_canonical,
)
from m3t.tokenizers.vae import MotionTokenizer


def _padded(model: MotionTokenizer, values: torch.Tensor) -> torch.Tensor:
    down = model.cfg.downsample
    return pad_to_multiple(values[None].float(), down, minimum=down)


@torch.no_grad()
def encode_clip(model: MotionTokenizer, values: np.ndarray | torch.Tensor) -> np.ndarray:
    """(T, D) canonical parameters -> (ceil(T / downsample),) int64 tokens (short clips are edge-padded)."""
    x = _padded(model, torch.as_tensor(values)).to(model.mean.device)
    return model.encode(x)[0].cpu().numpy()


@torch.no_grad()
def reconstruct_clip(model: MotionTokenizer, values: np.ndarray | torch.Tensor) -> torch.Tensor:
    """(T, D) canonical parameters -> (T, D) reconstruction through the quantiser."""
    values = torch.as_tensor(values)
    x = _padded(model, values).to(model.mean.device)
    return model(x).recon[0, : values.shape[0]].float().cpu()


@torch.no_grad()
def decode_streams(models: dict[str, MotionTokenizer], tokens: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Token streams (each (N,)) -> body-model parameters (N * downsample, D_m) per modality.

    The inverse of tokenisation: each stream through its group's frozen decoder, left hands mirrored back.
    """
    params = {}
    for stream in STREAMS:
        if stream.name not in tokens:
            raise KeyError(f"no tokens for stream {stream.name!r}; expected {[s.name for s in STREAMS]}")
        model = models[next(g for g, streams in GROUPS.items() if stream in streams)]
        idx = torch.as_tensor(np.asarray(tokens[stream.name]), dtype=torch.long, device=model.mean.device)[None]
        values = model.decode(idx)[0].float().cpu()
        params[stream.modality] = from_canonical(values, stream).numpy()
    return params


@dataclass
class ReconstructionProbe:
    """Validation clips + per-stream vertex regions, measured after every evaluation epoch. The reference
    vertices are posed once and kept when the clips hold at most ``cache_frames`` frames (up to 2,000 vertices
    per region: ~0.5 GB per stream at 20,000 frames); a larger set, such as every dev clip of the paper's
    three corpora (~0.7M frames), poses them again at each measurement instead of holding tens of GB."""

    body: BodyModel
    group: str
    clips: Sequence[FittedClip]
    max_frames: int = 2000  # 0 = every clip
    cache_frames: int = 20_000

    def __post_init__(self) -> None:
        self.streams = GROUPS[self.group]
        frames, clips = 0, []
        for clip in self.clips:  # cap the work per evaluation; clips are taken in order
            if 0 < self.max_frames <= frames:
                break
            clips.append(clip)
            frames += clip.num_frames
        self.clips = clips
        self.keypoints, self._inputs = {}, []
        for stream in self.streams:
            self.keypoints[stream.modality] = region_keypoints(self.body, stream_vertex_region(self.body, stream.modality))
        cache = frames <= self.cache_frames
        for clip in self.clips:
            params = as_tensors(clip.params)
            identity = torch.as_tensor(np.asarray(clip.identity), dtype=torch.float32)
            self._inputs.append((params, identity, self._truth(params, identity) if cache else None))

    def _truth(self, params: dict[str, torch.Tensor], identity: torch.Tensor) -> dict[str, torch.Tensor]:
        """{modality: (T, R, 3)} reference vertices of each stream's region."""
        return {s.modality: region_vertices(self.body, params, identity, self.keypoints[s.modality])
                for s in self.streams}

    @torch.no_grad()
    def measure(self, model: MotionTokenizer) -> dict[str, float]:
        """Frame-weighted means over the clips and streams: ``vpe_mm``, ``pa_vpe_mm``, ``param_l2``."""
        if not self.clips:
            return {}
        was_training = model.training
        model.eval()
        sums: dict[str, list[tuple[float, int]]] = {}
        for params, identity, truth in self._inputs:
            truth = truth if truth is not None else self._truth(params, identity)
            for stream in self.streams:
                values = params[stream.modality]
                recon = from_canonical(reconstruct_clip(model, to_canonical(values, stream)), stream)
                pred = region_vertices(self.body, {**params, stream.modality: recon}, identity, self.keypoints[stream.modality])
                errors = vertex_errors_mm(pred, truth[stream.modality])
                errors["param_l2"] = float((recon - values).pow(2).sum(-1).sqrt().mean())
                for key, value in errors.items():
                    sums.setdefault(key, []).append((value, values.shape[0]))
        model.train(was_training)
        return {k: float(np.average([v for v, _ in pairs], weights=[w for _, w in pairs])) for k, pairs in sums.items()}
