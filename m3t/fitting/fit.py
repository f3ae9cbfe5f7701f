"""Refinement of body-model parameters against 2D keypoints (M3T Appendix C, Eq. A.3), one clip or many.

    L_fit = w_kp L_kp + w_acc L_acc + w_reg L_reg,   (w_kp, w_acc, w_reg) = (1.0, 0.5, 0.01)

- ``L_kp``: confidence-weighted squared reprojection error in pixels; missing points (NaN or zero
  confidence) are masked. Each landmark part (pose, hands, face) is averaged separately and the parts are
  averaged, so the 468 face points do not drown the 21 points of a hand.
- ``L_acc``: squared acceleration of the model keypoints in cm / frame^2 (temporal smoothness).
- ``L_reg``: squared distance of every parameter to the tracker initialisation.

:func:`fit_tracks` fits several clips of one signer in one batch: their frames are packed along the batch
axis, each clip has its own camera and its own terms (the acceleration never spans two clips), the objective
is the sum of the clips' objectives, and the identity (the body shape) is one, shared by every clip: the
paper's static per-signer shape (with ``lbfgs_batched`` / ``lbfgs_lockstep``, one per clip unless given). :func:`fit_track` is the
one-clip case.

Four solvers (``fitting.solver``), each after a camera-only stage that places the body in the image using the
torso and head points:

- ``lbfgs``: L-BFGS with a strong-Wolfe line search and a convergence test
  (:func:`m3t.fitting.solvers.minimise`);
- ``lbfgs_batched`` (default): the ``lbfgs`` algorithm run for every clip of a batch on its own (its own optimiser,
  line searches, convergence test and identity), one objective evaluation serving them all
  (:func:`m3t.fitting.lbfgs.minimise_batched`): each clip fitted as its own fit would be, at a batch's speed;
- ``lbfgs_lockstep``: a vectorised L-BFGS per clip with a backtracking line search, in lock-step over a batch
  (:mod:`m3t.fitting.lockstep`: no per-clip Python bookkeeping, for large batches on a GPU);
- ``adam``: the first solver, a fixed number of Adam steps with a cosine learning-rate decay.

The body root stays at the origin; the camera's extrinsics carry the global placement. Only the sparse
keypoint forward is evaluated.

Axis legend: C clips, B frames of all clips, T frames of one clip, K landmarks, D per-frame modality dim.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from m3t.body.protocol import BodyModel, Correspondence
from m3t.body.rotations import matrix_to_6d, sixd_to_matrix
from m3t.camera import look_at, project
from m3t.fitting.config import FittingConfig
from m3t.fitting.objective import ClipPack, ClipTerms
from m3t.fitting.solvers import solve
from m3t.runtime import choose_device
from m3t.trackers.track import Track, landmark_slices


@dataclass(frozen=True)
class FitResult:
    params: dict[str, np.ndarray]  # modality -> (T, D) float32
    identity: np.ndarray  # (P,)
    camera: dict  # fitted camera (intrinsics + extrinsics), JSON-able
    metrics: dict[str, float]
    loss_curve: list[float] = field(default_factory=list)


def _intrinsics(track: Track, cfg: FittingConfig) -> torch.Tensor:
    if np.isfinite(track.intrinsics).all():
        return torch.as_tensor(track.intrinsics, dtype=torch.float32)
    w, h = track.image_size
    f = cfg.focal_guess * max(w, h)
    return torch.tensor([f, f, w / 2.0, h / 2.0])


def _init_extrinsics(body: BodyModel, identity: torch.Tensor, cfg: FittingConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """A frontal camera at ``cfg.camera_distance`` looking at the chest (between neck and spine)."""
    rest = body.rest_params(1)
    device = next(iter(rest.values())).device
    joints = body.forward(rest, identity.to(device)).joints[0].cpu()
    names = list(body.joint_names)
    chest = joints[[i for i, n in enumerate(names) if n.startswith(("neck", "spine"))]].mean(0).numpy()
    up = np.array([0.0, 0.0, 1.0])
    # The model faces -y (Anny) by convention of the protocol's layouts; look at its front.
    eye = chest + np.array([0.0, -cfg.camera_distance, 0.0])
    rot = look_at(eye, chest, up)
    return torch.tensor(rot, dtype=torch.float32), torch.tensor(-rot @ eye, dtype=torch.float32)


def fit_track(
    track: Track,
    body: BodyModel,
    cfg: FittingConfig,
    correspondence: Correspondence | None = None,
) -> FitResult:
    """Fit body-model parameters to one clip's 2D track, starting from the track's 3D initialisation (or
    the rest pose when the tracker gave none)."""
    return fit_tracks([track], body, cfg, correspondence)[0]


def fit_tracks(
    tracks: list[Track],
    body: BodyModel,
    cfg: FittingConfig,
    correspondence: Correspondence | None = None,
    identity: np.ndarray | None = None,
) -> list[FitResult]:
    """Fit several clips of one signer in one batch, with one shared identity; one :class:`FitResult` per track
    (all carrying that identity). Each clip starts from its track's 3D initialisation (or the rest pose).
    ``identity``: the signer's identity when already known (held fixed then), else it starts from the body
    model's default and is fitted when ``fitting.fit_identity``."""
    if not tracks:
        return []
    sets = {t.landmark_set for t in tracks}
    if len(sets) > 1:
        raise ValueError(f"tracks of one batch must share a landmark set; got "
                         f"{[t.landmark_set for t in tracks]} (one per track)")
    device = choose_device(cfg.device)
    if device.type != "cpu":
        body = body.to(device)  # type: ignore[attr-defined]
    layout = body.layout
    pack = ClipPack([t.num_frames for t in tracks], device)
    correspondence = correspondence or body.correspondence(tracks[0].landmark_set)
    kpset = body.keypoint_set(correspondence)
    valid = torch.as_tensor(correspondence.valid, device=device)
    target = torch.cat([torch.as_tensor(np.nan_to_num(t.keypoints, nan=0.0)) for t in tracks]).to(device)
    conf = torch.cat([torch.as_tensor(t.confidence) for t in tracks]).to(device) * valid
    empty = [str(i) for i, sl in enumerate(pack.slices) if float(conf[sl].sum()) == 0]
    if empty:
        what = "the track has" if len(tracks) == 1 else f"track(s) {', '.join(empty)} of the batch have"
        raise ValueError(f"{what} no visible landmark with a body-model correspondence in any frame")
    intrinsics = torch.stack([_intrinsics(t, cfg) for t in tracks]).to(device)  # (C, 4)
    parts = list(landmark_slices(tracks[0].landmark_set).values())
    terms = ClipTerms(pack, conf, parts, valid)

    inits = []
    for t in tracks:
        if t.init is not None:
            one = {k: torch.as_tensor(t.init[k]) for k in layout.names}
            layout.check(one)
        else:
            one = {k: v.cpu() for k, v in body.rest_params(t.num_frames).items()}
        inits.append(one)
    init = {k: torch.cat([one[k] for one in inits]).to(device) for k in layout.names}
    rot_streams = [m.name for m in layout.modalities if m.kind == "rotation6d"]
    scalar_streams = [m.name for m in layout.modalities if m.kind == "scalar"]
    # Every optimised tensor, by name; the objective reads them from here (the lock-step solver swaps in views
    # of its flat vector while it runs). Bounded streams (Anny's facial actions and phenotypes live in [0, 1]) are
    # optimised directly, enter the objective clamped and are projected back after each step or round (a
    # sigmoid would freeze parameters that start at 0).
    opt = {k: init[k].clone().requires_grad_(True) for k in [*rot_streams, *scalar_streams]}
    known = identity is not None
    identity0 = body.default_identity().to(device)
    if known:
        identity0 = torch.as_tensor(identity, dtype=identity0.dtype, device=device)
    # lbfgs_batched and lbfgs_lockstep fit every clip on its own (its own identity too, unless the signer's is given)
    per_clip_identity = cfg.per_clip_problems and not known
    shape = {"identity_index": pack.clip} if per_clip_identity else {}
    opt["identity"] = (identity0.expand(len(tracks), -1) if per_clip_identity else identity0).clone() \
        .requires_grad_(cfg.fit_identity and not known)

    rot0, trans0 = _init_extrinsics(body, identity0.cpu(), cfg)
    opt["cam_rot"] = matrix_to_6d(rot0).to(device).repeat(len(tracks), 1).requires_grad_(True)  # (C, 6)
    opt["cam_trans"] = trans0.to(device).repeat(len(tracks), 1).requires_grad_(True)  # (C, 3)
    frame_intrinsics = intrinsics[pack.clip]

    def current_params() -> dict[str, torch.Tensor]:
        out = {k: opt[k] for k in rot_streams}
        out.update({k: opt[k].clamp(*layout[k].bounds) if layout[k].bounds is not None else opt[k]
                    for k in scalar_streams})
        return out

    def current_identity() -> torch.Tensor:
        ident = opt["identity"]
        return ident if layout.identity_bounds is None else ident.clamp(*layout.identity_bounds)

    def uv_of(points: torch.Tensor) -> torch.Tensor:
        return project(points, sixd_to_matrix(opt["cam_rot"])[pack.clip], opt["cam_trans"][pack.clip],
                       frame_intrinsics)

    def keypoints_uv(params: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        points = body.forward_keypoints(params, current_identity(), kpset, **shape)  # (B, K, 3)
        return points, uv_of(points)

    curve: list[float] = []
    # Stage 1: camera only, against the torso and head (arms and hands are far from the rest pose).
    torso_conf = torch.zeros_like(conf)
    torso_conf[:, parts[0]] = conf[:, parts[0]]
    torso_conf[:, parts[0].start + 13: parts[0].start + 23] = 0.0  # elbows, wrists and hand points of the pose part
    if float(torso_conf.sum()) > 0:
        torso = ClipTerms(pack, torso_conf, [parts[0]], valid)
        with torch.no_grad():
            rest_points = body.forward_keypoints(current_params(), current_identity(), kpset, **shape)
        solve(opt, lambda: torso.reprojection(uv_of(rest_points), target), ["cam_rot", "cam_trans"], "camera",
              cfg.lr * 2, [], cfg, pack)

    # Stage 2: everything, with the full objective (the sum of the clips' objectives).
    bounds = {k: layout[k].bounds for k in scalar_streams if layout[k].bounds is not None}
    if layout.identity_bounds is not None:
        bounds["identity"] = layout.identity_bounds

    def bounded() -> None:
        with torch.no_grad():
            for k in scalar_streams:
                if layout[k].bounds is not None:
                    opt[k].clamp_(*layout[k].bounds)
            if layout.identity_bounds is not None:
                opt["identity"].clamp_(*layout.identity_bounds)

    def full_loss() -> torch.Tensor:
        params = current_params()
        points, uv = keypoints_uv(params)
        return (cfg.w_kp * terms.reprojection(uv, target) + cfg.w_acc * terms.acceleration(points)
                + cfg.w_reg * terms.regulariser(params, init))

    names = [*rot_streams, *scalar_streams, *(["identity"] if opt["identity"].requires_grad else []),
             "cam_rot", "cam_trans"]
    # lbfgs_batched / lbfgs_lockstep: each clip's own curve of the full stage
    clip_curves = solve(opt, full_loss, names, "full", cfg.lr, curve, cfg, pack, bounds, project_bounds=bounded)

    with torch.no_grad():
        params = current_params()
        params = {k: (matrix_to_6d(sixd_to_matrix(v.reshape(v.shape[0], -1, 6))).reshape(v.shape[0], -1)
                      if k in rot_streams else v) for k, v in params.items()}  # store orthonormal 6D
        _, uv = keypoints_uv(params)
        err_all = torch.linalg.norm(uv - target, dim=-1)
        rotations = sixd_to_matrix(opt["cam_rot"])
        ident = opt["identity"].detach().cpu().numpy().astype(np.float32)
        results = []
        for c, (track, sl) in enumerate(zip(tracks, pack.slices)):
            err = err_all[sl][conf[sl] > 0]
            own_curve = clip_curves[c] if clip_curves else curve
            metrics = {"reproj_px": float(err.mean()), "reproj_px_p95": float(torch.quantile(err, 0.95)),
                       "final_loss": own_curve[-1] if own_curve else float("nan")}
            fx, fy, cx, cy = (float(v) for v in intrinsics[c].cpu())
            camera = {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "rotation": rotations[c].cpu().tolist(),
                      "translation": opt["cam_trans"][c].cpu().tolist(),
                      "width": track.image_size[0], "height": track.image_size[1]}
            results.append(FitResult(
                params={k: v[sl].detach().cpu().numpy().astype(np.float32) for k, v in params.items()},
                identity=ident[c] if per_clip_identity else ident, camera=camera, metrics=metrics,
                loss_curve=list(own_curve)))
    return results
