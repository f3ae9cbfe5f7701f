"""The body-model protocol every downstream stage programs against.

A body model declares a :class:`ModalityLayout` (which streams exist and their per-frame dims), maps
per-frame parameters to joints / vertices (:meth:`BodyModel.forward`) and, for fitting, to a small set of
keypoints only (:meth:`BodyModel.forward_keypoints`). Nothing downstream hard-codes a dimension: it asks
the layout.

Axis legend: B batch (frames), V vertices, J joints, K keypoints, D per-frame feature dim.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Mapping, Protocol

import numpy as np
import torch

Params = Mapping[str, torch.Tensor]
"""Per-frame parameters: modality name -> (B, D_m)."""


def as_tensors(params: Mapping[str, np.ndarray]) -> dict[str, torch.Tensor]:
    """numpy (T, D) per modality -> float32 tensors (the form :meth:`BodyModel.forward` takes)."""
    return {k: torch.as_tensor(np.asarray(v), dtype=torch.float32) for k, v in params.items()}


STREAM_ORDER: tuple[str, ...] = ("body", "left_hand", "right_hand", "face")
"""The project's one order of the motion streams (M3T's {body, left hand, right hand, face}): token shard
columns, the SMLM's heads and fused inputs, and every per-stream loop follow it."""


@dataclass(frozen=True)
class Modality:
    """One parameter stream. ``kind='rotation6d'``: one 6D rotation per label; ``'scalar'``: one value per
    label (e.g. facial-action weights, expression coefficients)."""

    name: str
    kind: Literal["rotation6d", "scalar"]
    labels: tuple[str, ...]
    mirror_of: str | None = None  # the stream this one mirrors into (left hand <-> right hand)
    bounds: tuple[float, float] | None = None  # valid range of scalar values (Anny facial actions: [0, 1])

    @property
    def dim(self) -> int:
        return len(self.labels) * (6 if self.kind == "rotation6d" else 1)


@dataclass(frozen=True)
class ModalityLayout:
    modalities: tuple[Modality, ...]
    identity_labels: tuple[str, ...]
    identity_bounds: tuple[float, float] | None = None

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(m.name for m in self.modalities)

    @property
    def dims(self) -> dict[str, int]:
        return {m.name: m.dim for m in self.modalities}

    @property
    def identity_dim(self) -> int:
        return len(self.identity_labels)

    def __getitem__(self, name: str) -> Modality:
        for modality in self.modalities:
            if modality.name == name:
                return modality
        raise KeyError(f"no modality {name!r} in layout; available: {', '.join(self.names)}")

    def check(self, params: Params) -> int:
        """Validate a parameter dict against the layout; return the batch size B."""
        missing = set(self.names) - set(params)
        if missing:
            raise ValueError(f"parameters lack modalities {sorted(missing)}; layout has {list(self.names)}")
        sizes = {p.shape[0] for p in params.values()}
        if len(sizes) != 1:
            raise ValueError(f"modalities disagree on the number of frames: {sizes}")
        for name, dim in self.dims.items():
            if params[name].shape[-1] != dim:
                raise ValueError(f"modality {name!r} has dim {params[name].shape[-1]}, layout says {dim}")
        return sizes.pop()


@dataclass(frozen=True)
class BodyOutput:
    """joints: (B, J, 3); vertices: (B, V, 3) or None when only keypoints were asked for."""

    joints: torch.Tensor
    vertices: torch.Tensor | None


@dataclass(frozen=True)
class Correspondence:
    """Where each tracker landmark sits on the body model.

    ``kind[k]``: 0 = vertex ``index[k]``, 1 = joint (bone head) ``index[k]``, -1 = no correspondence (the
    landmark is given zero confidence, never an invented position).
    """

    names: tuple[str, ...]
    kind: np.ndarray  # (K,) int
    index: np.ndarray  # (K,) int

    @property
    def valid(self) -> np.ndarray:
        return self.kind >= 0


@dataclass(frozen=True)
class KeypointIndex:
    """What a sparse forward needs for K points, each a vertex or a joint (bone head) of the model.

    vertex_index / joint_index hold 0 where the point is not of that kind; valid is False where the
    correspondence has none (the point is returned as zeros).
    """

    is_vertex: torch.Tensor  # (K,) bool
    vertex_index: torch.Tensor  # (K,) long
    joint_index: torch.Tensor  # (K,) long
    valid: torch.Tensor  # (K,) bool

    @classmethod
    def from_correspondence(cls, correspondence: Correspondence, device: torch.device | str) -> KeypointIndex:
        kind = torch.as_tensor(correspondence.kind)
        index = torch.as_tensor(correspondence.index).long()
        is_vertex = kind == 0
        return cls(
            is_vertex=is_vertex.to(device),
            vertex_index=torch.where(is_vertex, index, 0).to(device),
            joint_index=torch.where(kind == 1, index, 0).to(device),
            valid=(kind >= 0).to(device),
        )


class BodyModel(Protocol):
    """What fitting, tokenizers and renderers need from a body model."""

    name: str
    layout: ModalityLayout
    joint_names: tuple[str, ...]
    joint_parents: tuple[int, ...]  # parent index per joint, -1 for the root
    faces: np.ndarray  # (F, 3) int

    def rest_params(self, batch: int) -> dict[str, torch.Tensor]:
        """Parameters of the rest pose, each (batch, D_m)."""

    def default_identity(self) -> torch.Tensor:
        """(identity_dim,) neutral identity."""

    def forward(self, params: Params, identity: torch.Tensor) -> BodyOutput:
        """Full forward: joints and all vertices. identity: (identity_dim,) or (B, identity_dim)."""

    def keypoint_set(self, correspondence: Correspondence) -> object:
        """Precompute what :meth:`forward_keypoints` needs for these landmarks (done once per fit)."""

    def forward_keypoints(self, params: Params, identity: torch.Tensor, keypoints: object,
                          identity_index: torch.Tensor | None = None) -> torch.Tensor:
        """Sparse forward: (B, K, 3) positions of the landmarks only (zeros where there is no correspondence).
        ``identity`` (P,) or (B, P); with ``identity_index`` (B,), (C, P) identities and each frame's row."""

    def correspondence(self, landmark_set: str) -> Correspondence:
        """The stored landmark correspondence for a tracker layout (e.g. ``'mediapipe_holistic'``)."""
