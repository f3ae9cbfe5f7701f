"""Rotation representations used project-wide.

Every pose stream is stored in the continuous 6D representation of Zhou et al. (2019): the first two
columns of the rotation matrix, flattened as ``(r00, r10, r20, r01, r11, r21)``. roma implements the
Gram-Schmidt mapping; these wrappers fix the memory layout once so that shards, tokenizers and models agree.

Axis legend: ``...`` any leading axes (batch, time, joint).
"""
from __future__ import annotations

import roma
import torch


def matrix_to_6d(rotmat: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``(..., 3, 3)`` -> 6D vectors ``(..., 6)`` (first two columns, column-major)."""
    return rotmat[..., :, :2].transpose(-1, -2).reshape(*rotmat.shape[:-2], 6)


def sixd_to_matrix(sixd: torch.Tensor) -> torch.Tensor:
    """6D vectors ``(..., 6)`` -> rotation matrices ``(..., 3, 3)`` via Gram-Schmidt (roma)."""
    columns = sixd.reshape(*sixd.shape[:-1], 2, 3).transpose(-1, -2)  # (..., 3, 2)
    return roma.special_gramschmidt(columns)


def identity_6d(*shape: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """Identity rotations in 6D, shape ``(*shape, 6)``."""
    eye = torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0], dtype=dtype, device=device)
    return eye.expand(*shape, 6).clone()


def euler_to_6d(angles: torch.Tensor, convention: str = "XYZ") -> torch.Tensor:
    """Intrinsic Euler angles in radians ``(..., 3)`` -> 6D ``(..., 6)``."""
    return matrix_to_6d(roma.euler_to_rotmat(convention, angles))


REFLECT_X = torch.diag(torch.tensor([-1.0, 1.0, 1.0]))


def mirror_rotations(sixd: torch.Tensor) -> torch.Tensor:
    """Mirror joint rotations across the body's sagittal (x = 0) plane.

    The left hand is mirrored into a right hand (and back) by conjugating every joint rotation with the
    reflection ``M = diag(-1, 1, 1)``: ``R' = M R M``. This holds for any body model whose joint frames are
    expressed in body-aligned axes with x pointing to the side (SMPL-X / MANO and Anny's ``local-ref``
    parameterisation alike). Applying it twice is the identity.

    Parameters
    ----------
    sixd : (..., 6) rotations in the 6D representation, or (..., J*6) flattened per joint.
    """
    flat = sixd.reshape(*sixd.shape[:-1], -1, 6)  # (..., J, 6)
    # M R M flips the sign of entries (0,1), (0,2), (1,0), (2,0); in 6D layout (r00,r10,r20,r01,r11,r21)
    # that is r10, r20 and r01.
    sign = flat.new_tensor([1.0, -1.0, -1.0, -1.0, 1.0, 1.0])
    return (flat * sign).reshape(sixd.shape)
