"""Fitted clips seen as skeleton sequences (SGSA's skeletal graphs, :mod:`m3t.body.skeleton`): what the skeletal
production models train on and what the skeleton back-translation judge reads.

A clip's skeleton is its fitted motion posed with its own signer identity into the graph's joints (metres), then
normalised (:func:`m3t.body.skeleton_points.normalise`: neck-centred per frame, divided by the clip's mean shoulder
width). ``holistic`` graphs take the body model's MediaPipe-Holistic correspondence, the point layout of ``.pose``
files; ``body`` graphs the metric keypoints of the DTW evaluation.

Axis legend: T frames, J graph joints, C = 3 J coordinates.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from tqdm.auto import tqdm

from m3t.body.protocol import BodyModel, as_tensors
from m3t.body.skeleton import SkeletonGraph
from m3t.body.skeleton_points import body_points, holistic_points, normalise
from m3t.shards.schema import FittedClip

SKELETON_STREAM = "skeleton"  # the one stream name of a skeleton clip's params


@dataclass(frozen=True, eq=False)
class SkeletonClip:
    fitted: FittedClip
    points: np.ndarray  # (T, J, 3) float64 metres
    coords: np.ndarray  # (T, C) float32 normalised
    scale: float  # metres per normalised unit (the clip's mean shoulder width)

    @property
    def clip_id(self) -> str:
        return self.fitted.clip.id

    def as_fitted(self) -> FittedClip:
        """The clip with ``params = {"skeleton": coords}``: the input of a skeleton back-translation model."""
        f = self.fitted
        return FittedClip(f.clip, f.key, {SKELETON_STREAM: self.coords}, f.identity, f.camera, f.metrics, f.body_model)


@torch.no_grad()
def graph_points(body: BodyModel, params: Mapping[str, np.ndarray], identity: np.ndarray,
                 graph: SkeletonGraph) -> np.ndarray:
    """(T, J, 3) float64 metres of ``graph``'s joints for a parameter sequence of ``body``."""
    if graph.name.startswith("holistic"):
        corr = body.correspondence("mediapipe_holistic")
        ident = torch.as_tensor(np.asarray(identity), dtype=torch.float32)
        points = body.forward_keypoints(as_tensors(params), ident, body.keypoint_set(corr)).numpy()
        return holistic_points(points.astype(np.float64), corr.names, graph)
    return body_points(body, params, identity, graph)


def skeleton_clip(body: BodyModel, fitted: FittedClip, graph: SkeletonGraph) -> SkeletonClip:
    """One fitted clip posed into ``graph`` and normalised; a degenerate clip raises ``ValueError`` naming it."""
    points = graph_points(body, fitted.params, fitted.identity, graph)
    try:
        coords, scale = normalise(points, graph)
    except ValueError as exc:
        raise ValueError(f"clip {fitted.clip.id!r}: {exc}") from exc
    return SkeletonClip(fitted, points, coords, scale)


def skeleton_clips(body: BodyModel, clips: Sequence[FittedClip], graph: SkeletonGraph, progress: bool = False,
                   desc: str = "skeletons") -> list[SkeletonClip]:
    """:func:`skeleton_clip` of every clip with frames (clips with none are left out), order kept."""
    return [skeleton_clip(body, c, graph) for c in tqdm(clips, desc=desc, disable=not progress) if c.num_frames]
