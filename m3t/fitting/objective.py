"""The fitting objective's terms (M3T Appendix C, Eq. A.3): for one clip (:func:`reprojection_loss`,
:func:`acceleration_loss`) and for a batch of clips packed along one axis (:class:`ClipPack`, :class:`ClipTerms`),
each clip's terms its own.

Axis legend: C clips, B frames of all clips, T frames of one clip, K landmarks, D per-frame modality dim.
"""
from __future__ import annotations

import numpy as np
import torch


def reprojection_loss(pred_uv: torch.Tensor, target: torch.Tensor, conf: torch.Tensor, parts: list[slice]) -> torch.Tensor:
    """Mean over parts of the confidence-weighted squared pixel error; pred/target (T, K, 2), conf (T, K)."""
    sq = ((pred_uv - target) ** 2).sum(-1) * conf  # (T, K)
    losses = [sq[:, p].sum() / conf[:, p].sum() for p in parts if conf[:, p].sum() > 0]
    return torch.stack(losses).mean()


def acceleration_loss(points: torch.Tensor) -> torch.Tensor:
    """Mean squared acceleration (cm / frame^2)^2 of (T, K, 3) points in metres; 0 for T < 3."""
    if points.shape[0] < 3:
        return points.new_zeros(())
    acc = (points[2:] - 2 * points[1:-1] + points[:-2]) * 100.0
    return (acc ** 2).sum(-1).mean()


class ClipPack:
    """Several clips' frames along one batch axis, and the per-clip reductions of the objective's terms.

    Per-clip sums are segment sums (``index_add``) over the rows a clip owns, never products with 0/1 weight
    matrices: a value of one clip (an infinity or NaN at a wild line-search trial of its own) then reaches no
    other clip's loss or gradient, as ``0 x inf`` in a weight product would. ``triplets``: the acceleration
    triplets (t - 1, t, t + 1) whose three frames lie in one clip, by their first frame, with their clip and the
    weight of the mean over that clip's triplets.
    """

    def __init__(self, lengths: list[int], device: torch.device):
        self.lengths = lengths
        self.clips = len(lengths)
        self.clip = torch.repeat_interleave(torch.arange(len(lengths), device=device),
                                            torch.as_tensor(lengths, device=device))  # (B,) clip of each frame
        starts = np.cumsum([0] + lengths[:-1])
        self.slices = [slice(int(a), int(a) + n) for a, n in zip(starts, lengths)]
        self.frame_weight = (1.0 / torch.as_tensor(lengths, dtype=torch.float32, device=device).clamp(min=1))[
            self.clip]  # (B,) 1 / frames of the frame's clip
        first, owner, weight = [], [], []
        for c, sl in enumerate(self.slices):
            count = sl.stop - sl.start - 2
            if count >= 1:
                first.extend(range(sl.start, sl.stop - 2))
                owner.extend([c] * count)
                weight.extend([1.0 / count] * count)
        self.triplet_first = torch.as_tensor(first, dtype=torch.long, device=device)
        self.triplet_clip = torch.as_tensor(owner, dtype=torch.long, device=device)
        self.triplet_weight = torch.as_tensor(weight, dtype=torch.float32, device=device)

    def clip_sum(self, values: torch.Tensor, index: torch.Tensor | None = None) -> torch.Tensor:
        """(C, ...) sums of ``values`` (N, ...) by clip (``index``: the clip of each row, default every frame's)."""
        index = self.clip if index is None else index
        return values.new_zeros((self.clips, *values.shape[1:])).index_add(0, index, values)


class ClipTerms:
    """The objective's three terms per clip, (C,) each; for one clip exactly :func:`reprojection_loss`,
    :func:`acceleration_loss` and the mean over streams of the mean squared distance to the initialisation."""

    def __init__(self, pack: ClipPack, conf: torch.Tensor, parts: list[slice], valid: torch.Tensor):
        self.pack = pack
        self.conf = conf
        membership = torch.zeros(conf.shape[1], len(parts), dtype=conf.dtype, device=conf.device)  # (K, parts)
        for i, p in enumerate(parts):
            membership[p, i] = 1.0
        self.membership = membership
        norm = pack.clip_sum(conf @ membership)  # (C, parts) summed confidence
        has_part = norm > 0
        # each part's weighted squared error / its summed confidence, averaged over the parts the clip has
        self.part_weights = has_part / torch.where(has_part, norm, torch.ones_like(norm)) \
            / has_part.sum(1, keepdim=True).clamp(min=1)
        # mean over the valid points of a squared acceleration in cm (points are in metres)
        valid = valid.to(conf.dtype)
        self.point_weights = valid * 100.0 ** 2 / valid.sum().clamp(min=1)  # (K,)
        self._stream_weights: dict[tuple, torch.Tensor] = {}

    def reprojection(self, uv: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        sq = ((uv - target) ** 2).sum(-1) * self.conf  # (B, K)
        return (self.pack.clip_sum(sq @ self.membership) * self.part_weights).sum(1)

    def acceleration(self, points: torch.Tensor) -> torch.Tensor:
        first = self.pack.triplet_first
        acc = points[first + 2] - 2 * points[first + 1] + points[first]  # (triplets, K, 3), inside clips only
        return self.pack.clip_sum(((acc ** 2).sum(-1) @ self.point_weights) * self.pack.triplet_weight,
                                  self.pack.triplet_clip)

    def regulariser(self, params: dict[str, torch.Tensor], init: dict[str, torch.Tensor]) -> torch.Tensor:
        dims = tuple(params[k].shape[1] for k in params)
        weights = self._stream_weights.get(dims)
        if weights is None:  # the mean over streams of each stream's mean over its dimensions
            weights = torch.cat([torch.full((d,), 1.0 / (d * len(dims))) for d in dims]).to(self.conf)
            self._stream_weights[dims] = weights
        diff = torch.cat([params[k] - init[k] for k in params], 1)  # (B, D)
        return self.pack.clip_sum(((diff ** 2) @ weights) * self.pack.frame_weight)
