"""NLF / WiLoR / Pixel3DMM outputs of a tiny clip, written beside its media in the formats the trackers'
public code produces, from known SMPL-FX ground truth (the synthetic SMPL-X / FLAME stand-ins of
:mod:`smplfx_fixtures`), so that tests can check what fusion recovers.

Formats, as the trackers' own code makes them:

- **Pixel3DMM**, ``src/pixel3dmm/tracking/tracker.py::Tracker.save_checkpoint``: ``torch.save`` of one dict
  per frame to ``<output>/<video>/checkpoint/{frame_id:05d}.frame`` (meshes go to ``<output>/<video>/mesh/``).
  One real row, keys and shapes (batch of one frame)::

      {'flame': {'exp': (1, 100), 'shape': (1, 300), 'eyes': (1, 12), 'eyelids': (1, 2), 'jaw': (1, 6),
                 'neck': (1, 6), 'R': (1, 6), 'R_rotation_matrix': (1, 3, 3), 't': (1, 3)},
       'img_size': (2,), 'frame_id': int, 'global_step': int,
       'camera': {'R_base_0': (1, 3, 3), 't_base_0': (1, 3), 'fl': (1, 1), 'pp': (1, 2)},
       'joint_transforms': (1, 5, 4, 4)}

  numpy arrays; rotations in PyTorch3D's 6D (``matrix_to_rotation_6d``: the first two rows).
- **WiLoR**, ``wilor/models/wilor.py::WiLoR.forward_step`` and ``wilor/models/heads/refinement_net.py``:
  ``out['pred_mano_params'] = {'global_orient': (B, 1, 3, 3), 'hand_pose': (B, 15, 3, 3), 'betas': (B, 10)}``
  (rotation matrices); ``demo.py``: ``batch['right']`` (B,) is the detector's class, 0 = left, and left hands
  are run as flipped right hands. WiLoR writes no parameter file itself: a clip's file stacks these rows per
  detection with ``frame_index``, ``is_right`` and the detector ``confidence`` (flat keys in ``.npz``,
  ``pred_mano_params`` nested in ``.pt``).
- **NLF**, ``detect_smpl_batched(frames, model_name='smplx')``: per-frame lists ``pose[t]`` (people, 165)
  axis-angle, ``betas[t]`` (people, 10), ``trans[t]`` (people, 3), ``boxes[t]`` (people, 5) with the score last;
  written as those lists (``.pt``) or stacked for the signer with NaN rows where no one was found (``.npz``).

Ground truth: :func:`smplfx_fixtures.smplfx_motion` parameters, SMPL-X betas and a FLAME shape. Gaps (the
defaults of the writers): NLF loses the signer in frame 2, WiLoR misses the right hand in frames 3-5 (and
sees a spurious, less confident right hand in frame 0), Pixel3DMM has no face in frames 6-7.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import roma
import torch
from corpus_fixtures import write_frames, write_video
from smplfx_fixtures import smplfx_motion

from m3t.body.rotations import sixd_to_matrix
from m3t.body.smplfx_build import SMPLX_JOINTS

MIRROR = np.diag([-1.0, 1.0, 1.0])
NLF_MISSING, WILOR_RIGHT_MISSING, PIXEL3DMM_MISSING = (2,), (3, 4, 5), (6, 7)
T = 10  # frames of the ``truth`` fixture's clip (tests/conftest.py)


@dataclass(frozen=True)
class GroundTruth:
    params: dict[str, torch.Tensor]  # SMPL-FX per-frame parameters, modality -> (T, D)
    rot: dict[str, np.ndarray]  # rotation modality -> (T, n, 3, 3); "jaw" -> (T, 3, 3)
    betas: np.ndarray  # (10,) SMPL-X betas (NLF's identity)
    flame_shape: np.ndarray  # (300,) FLAME shape (Pixel3DMM's identity)
    identity: np.ndarray  # (P,) the SMPL-FX identity these make

    @property
    def frames(self) -> int:
        return int(self.params["face"].shape[0])


def ground_truth(body, frames: int = 10, seed: int = 7) -> GroundTruth:
    params = smplfx_motion(body, frames=frames, seed=seed)
    rot = {k: sixd_to_matrix(v.reshape(frames, -1, 6)).double().numpy() for k, v in params.items() if k != "face"}
    rot["jaw"] = sixd_to_matrix(params["face"][:, 102:]).double().numpy()
    rng = np.random.default_rng(seed)
    betas, shape = rng.uniform(-1, 1, 10), rng.normal(0, 0.5, 300)
    identity = np.concatenate([betas, shape[: body.layout.identity_dim - 10]]).astype(np.float32)
    return GroundTruth(params, rot, betas, shape, identity)


def rot_err_deg(a6: np.ndarray, b_rot: np.ndarray) -> float:
    """Largest geodesic angle (degrees) between 6D rotations ``a6`` (..., n * 6) and matrices ``b_rot`` (..., n, 3, 3)."""
    a = sixd_to_matrix(torch.as_tensor(a6, dtype=torch.float64).reshape(*b_rot.shape[:-2], 6))
    rel = a.transpose(-1, -2) @ torch.as_tensor(b_rot)
    return float(torch.rad2deg(roma.rotmat_geodesic_distance(rel, torch.eye(3, dtype=torch.float64))).max())


def pytorch3d_6d(rot: np.ndarray) -> np.ndarray:
    return rot[..., :2, :].reshape(*rot.shape[:-2], 6)  # first two rows, as PyTorch3D stores it


# ------------------------------------------------------------------------------------------------ NLF
def write_nlf(path: Path, layout, truth: GroundTruth, missing: tuple[int, ...] = NLF_MISSING) -> Path:
    """``.npz``: stacked (T, 165) with NaN rows; ``.pt``: ``detect_smpl_batched``'s per-frame lists."""
    T = truth.frames
    pose = np.zeros((T, 55, 3))
    pose[:, 0] = (0.0, 3.1, 0.1)  # global orient, facing the camera; SMPL-FX leaves it to the camera
    for stream in ("body", "left_hand", "right_hand"):
        cols = [SMPLX_JOINTS.index(n) for n in layout[stream].labels]
        pose[:, cols] = roma.rotmat_to_rotvec(torch.as_tensor(truth.rot[stream])).numpy()
    pose[:, SMPLX_JOINTS.index("jaw")] = roma.rotmat_to_rotvec(torch.as_tensor(truth.rot["jaw"])).numpy()
    pose = pose.reshape(T, 165)
    betas, trans = np.tile(truth.betas, (T, 1)), np.tile([0.0, 0.2, 3.0], (T, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".pt":
        def person(a: np.ndarray, t: int) -> torch.Tensor:
            return torch.as_tensor(a[t:t + 1] if t not in missing else a[:0], dtype=torch.float32)
        boxes = np.tile([100.0, 50.0, 300.0, 400.0, 0.9], (T, 1))
        torch.save({k: [person(a, t) for t in range(T)] for k, a in
                    (("pose", pose), ("betas", betas), ("trans", trans), ("boxes", boxes))}, path)
    else:
        pose[list(missing)] = np.nan
        np.savez(path, pose=pose, betas=betas, trans=trans, confidence=np.full(T, 0.9))
    return path


# ---------------------------------------------------------------------------------------------- WiLoR
def write_wilor(path: Path, truth: GroundTruth, right_missing: tuple[int, ...] = WILOR_RIGHT_MISSING) -> Path:
    rows: dict[str, list] = {"frame_index": [], "is_right": [], "global_orient": [], "hand_pose": [], "betas": [],
                             "confidence": []}

    def add(t: int, right: int, hp: np.ndarray, go: np.ndarray, conf: float) -> None:
        for k, v in zip(rows, (t, right, go[None], hp, np.zeros(10), conf)):
            rows[k].append(v)

    for t in range(truth.frames):
        for side, right in (("right_hand", 1), ("left_hand", 0)):
            if right and t in right_missing:
                continue
            hp, go = truth.rot[side][t], np.eye(3)
            if not right:  # WiLoR predicts left hands as flipped right hands
                hp, go = MIRROR @ hp @ MIRROR, MIRROR @ go @ MIRROR
            add(t, right, hp, go, 0.95)
    add(0, 1, np.tile(np.eye(3), (15, 1, 1)), np.eye(3), 0.2)  # a spurious, less confident right hand
    arrays = {k: np.asarray(v) for k, v in rows.items()}
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".pt":
        mano = {k: torch.as_tensor(arrays.pop(k), dtype=torch.float32) for k in ("global_orient", "hand_pose", "betas")}
        torch.save({**{k: torch.as_tensor(v) for k, v in arrays.items()}, "pred_mano_params": mano}, path)
    else:
        np.savez(path, **arrays)
    return path


# ------------------------------------------------------------------------------------------ Pixel3DMM
def pixel3dmm_frame(truth: GroundTruth, t: int) -> dict:
    """One ``.frame`` dict, keys and shapes as ``save_checkpoint`` writes them (module docstring)."""
    face = truth.params["face"].numpy()
    eye6 = pytorch3d_6d(np.eye(3)[None]).astype(np.float32)
    return {
        "flame": {"exp": face[t:t + 1, :100].astype(np.float32),
                  "shape": truth.flame_shape[None].astype(np.float32),
                  "eyes": np.tile(eye6, (1, 2)), "eyelids": face[t:t + 1, 100:102].astype(np.float32),
                  "jaw": pytorch3d_6d(truth.rot["jaw"][t:t + 1]).astype(np.float32),
                  "neck": eye6, "R": eye6, "R_rotation_matrix": np.eye(3, dtype=np.float32)[None],
                  "t": np.zeros((1, 3), np.float32)},
        "img_size": np.array([512, 512]), "frame_id": t, "global_step": 100,
        "camera": {"R_base_0": np.eye(3, dtype=np.float32)[None], "t_base_0": np.zeros((1, 3), np.float32),
                   "fl": np.array([[4.0]], np.float32), "pp": np.zeros((1, 2), np.float32)},
        "joint_transforms": np.tile(np.eye(4, dtype=np.float32), (1, 5, 1, 1)),
    }


def write_pixel3dmm(output: Path, truth: GroundTruth, missing: tuple[int, ...] = PIXEL3DMM_MISSING) -> Path:
    """Pixel3DMM's per-clip output folder: ``checkpoint/*.frame`` plus a ``mesh/`` the readers ignore."""
    (output / "checkpoint").mkdir(parents=True, exist_ok=True)
    (output / "mesh").mkdir(exist_ok=True)
    for t in range(truth.frames):
        if t not in missing:
            torch.save(pixel3dmm_frame(truth, t), output / "checkpoint" / f"{t:05d}.frame")
    (output / "mesh" / "canonical.ply").write_text("ply\n")
    return output


# --------------------------------------------------------------------------------------- a whole clip
def write_media(folder: Path, name: str = "abc", kind: str = "video") -> Path:
    """A tiny clip's media: a video file, a ``.pose`` file (a few bytes: never decoded here) or a frame folder."""
    if kind == "frames":
        write_frames(folder / name, n=2)
        return folder / name
    path = folder / (f"{name}.mp4" if kind == "video" else f"{name}.pose")
    if kind == "video":
        write_video(path)
    else:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"\x00")
    return path


def output_paths(media: Path) -> dict[str, Path]:
    """Where the published layout puts each tracker's output beside ``media`` (``.npz`` files)."""
    stem = media.name if media.is_dir() else media.stem
    return {"nlf": media.parent / f"{stem}.nlf.npz", "wilor": media.parent / f"{stem}.wilor.npz",
            "pixel3dmm": media.parent / f"{stem}.pixel3dmm"}


def write_clip(folder: Path, body, truth: GroundTruth, trackers: tuple[str, ...] = ("nlf", "wilor", "pixel3dmm"),
               kind: str = "video", name: str = "abc", suffix: str = ".npz") -> Path:
    """Media plus the chosen trackers' outputs beside it (``suffix`` ``.pt`` writes NLF / WiLoR torch files);
    returns the media path."""
    media = write_media(folder, name, kind)
    paths = output_paths(media)
    if "nlf" in trackers:
        write_nlf(paths["nlf"].with_suffix(suffix), body.layout, truth)
    if "wilor" in trackers:
        write_wilor(paths["wilor"].with_suffix(suffix), truth)
    if "pixel3dmm" in trackers:
        write_pixel3dmm(paths["pixel3dmm"], truth)
    return media
