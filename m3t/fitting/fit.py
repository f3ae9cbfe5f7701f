"""Per-clip refinement of body-model parameters against 2D keypoints (M3T Appendix C, Eq. A.3).

    L_fit = w_kp L_kp + w_acc L_acc + w_reg L_reg,   (w_kp, w_acc, w_reg) = (1.0, 0.5, 0.01)

- ``L_kp``: confidence-weighted squared reprojection error in pixels; missing points (NaN or zero
  confidence) are masked. Each landmark part (pose, hands, face) is averaged separately and the parts are
  averaged, so the 468 face points do not drown the 21 points of a hand.
- ``L_acc``: squared acceleration of the model keypoints in cm / frame^2 (temporal smoothness).
- ``L_reg``: squared distance of every parameter to the tracker initialisation.

All frames of a clip are optimised together (one batch) with Adam, after a camera-only stage that
places the body in the image using the torso and head points. The body root stays at the origin; the
camera's extrinsics carry the global placement. Only the sparse keypoint forward is evaluated.

Axis legend: T frames, K landmarks, D per-frame modality dim.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from m3t.body.protocol import BodyModel, Correspondence
from m3t.body.rotations import matrix_to_6d, sixd_to_matrix
from m3t.camera import look_at, project
from m3t.fitting.config import FittingConfig
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
    joints = body.forward(body.rest_params(1), identity).joints[0]
    names = list(body.joint_names)
    chest = joints[[i for i, n in enumerate(names) if n.startswith(("neck", "spine"))]].mean(0).numpy()
    up = np.array([0.0, 0.0, 1.0])
    # The model faces -y (Anny) by convention of the protocol's layouts; look at its front.
    eye = chest + np.array([0.0, -cfg.camera_distance, 0.0])
    rot = look_at(eye, chest, up)
    return torch.tensor(rot, dtype=torch.float32), torch.tensor(-rot @ eye, dtype=torch.float32)


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


def fit_track(
    track: Track,
    body: BodyModel,
    cfg: FittingConfig,
    correspondence: Correspondence | None = None,
) -> FitResult:
    """Fit body-model parameters to one clip's 2D track, starting from the track's 3D initialisation (or
    the rest pose when the tracker gave none)."""
    device = choose_device(cfg.device)
    if device.type != "cpu":
        body = body.to(device)  # type: ignore[attr-defined]
    layout = body.layout
    T = track.num_frames
    correspondence = correspondence or body.correspondence(track.landmark_set)
    kpset = body.keypoint_set(correspondence)
    target = torch.as_tensor(np.nan_to_num(track.keypoints, nan=0.0), device=device)
    valid = torch.as_tensor(correspondence.valid, device=device)
    conf = torch.as_tensor(track.confidence, device=device) * valid
    if float(conf.sum()) == 0:
        raise ValueError("the track has no visible landmark with a body-model correspondence in any frame")
    intrinsics = _intrinsics(track, cfg).to(device)
    parts = list(landmark_slices(track.landmark_set).values())

    if track.init is not None:
        init = {k: torch.as_tensor(track.init[k], device=device) for k in layout.names}
        layout.check(init)
    else:
        init = {k: v.to(device) for k, v in body.rest_params(T).items()}
    rot_streams = [m.name for m in layout.modalities if m.kind == "rotation6d"]
    scalar_streams = [m.name for m in layout.modalities if m.kind == "scalar"]
    variables = {k: init[k].clone().requires_grad_(True) for k in rot_streams}
    # Bounded streams (Anny's facial actions and phenotypes live in [0, 1]) are optimised directly and
    # projected back after each step (a sigmoid would freeze parameters that start at 0).
    variables.update({k: init[k].clone().requires_grad_(True) for k in scalar_streams})
    identity0 = body.default_identity().to(device)
    identity = identity0.clone().requires_grad_(cfg.fit_identity)

    rot0, trans0 = _init_extrinsics(body, identity0.cpu(), cfg)
    cam_rot = matrix_to_6d(rot0).to(device).requires_grad_(True)
    cam_trans = trans0.to(device).requires_grad_(True)

    def current_params() -> dict[str, torch.Tensor]:
        out = {k: variables[k] for k in rot_streams}
        out.update({k: variables[k] for k in scalar_streams})
        return out

    def keypoints_uv(params: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        points = body.forward_keypoints(params, identity, kpset)  # (T, K, 3)
        return points, project(points, sixd_to_matrix(cam_rot), cam_trans, intrinsics)

    curve: list[float] = []
    # Stage 1: camera only, against the torso and head (arms and hands are far from the rest pose).
    torso_conf = torch.zeros_like(conf)
    torso_conf[:, parts[0]] = conf[:, parts[0]]
    torso_conf[:, parts[0].start + 13: parts[0].start + 23] = 0.0  # elbows, wrists and hand points of the pose part
    if float(torso_conf.sum()) > 0:
        opt = torch.optim.Adam([cam_rot, cam_trans], lr=cfg.lr * 2)
        with torch.no_grad():
            rest_points = body.forward_keypoints(current_params(), identity, kpset)
        for _ in range(cfg.camera_iterations):
            opt.zero_grad()
            uv = project(rest_points, sixd_to_matrix(cam_rot), cam_trans, intrinsics)
            loss = reprojection_loss(uv, target, torso_conf, [parts[0]])
            loss.backward()
            opt.step()

    # Stage 2: everything, with the full objective.
    opt = torch.optim.Adam([*variables.values(), identity, cam_rot, cam_trans], lr=cfg.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(1, cfg.iterations), eta_min=cfg.lr * 0.05)
    for _ in range(cfg.iterations):
        opt.zero_grad()
        params = current_params()
        points, uv = keypoints_uv(params)
        l_kp = reprojection_loss(uv, target, conf, parts)
        l_acc = acceleration_loss(points[:, valid])
        l_reg = torch.stack([((params[k] - init[k]) ** 2).mean() for k in params]).mean()
        loss = cfg.w_kp * l_kp + cfg.w_acc * l_acc + cfg.w_reg * l_reg
        loss.backward()
        opt.step()
        sched.step()
        with torch.no_grad():
            for k in scalar_streams:
                if layout[k].bounds is not None:
                    variables[k].clamp_(*layout[k].bounds)
            if layout.identity_bounds is not None:
                identity.clamp_(*layout.identity_bounds)
        curve.append(float(loss.detach()))

    with torch.no_grad():
        params = current_params()
        params = {k: (matrix_to_6d(sixd_to_matrix(v.reshape(T, -1, 6))).reshape(T, -1) if k in rot_streams else v)
                  for k, v in params.items()}  # store orthonormal 6D
        _, uv = keypoints_uv(params)
        visible = conf > 0
        err = torch.linalg.norm(uv - target, dim=-1)[visible]
        metrics = {"reproj_px": float(err.mean()), "reproj_px_p95": float(torch.quantile(err, 0.95)),
                   "final_loss": curve[-1] if curve else float("nan")}
        fx, fy, cx, cy = (float(v) for v in intrinsics.cpu())
        camera = {"fx": fx, "fy": fy, "cx": cx, "cy": cy,
                  "rotation": sixd_to_matrix(cam_rot).cpu().tolist(), "translation": cam_trans.cpu().tolist(),
                  "width": track.image_size[0], "height": track.image_size[1]}
    return FitResult(
        params={k: v.detach().cpu().numpy().astype(np.float32) for k, v in params.items()},
        identity=identity.detach().cpu().numpy().astype(np.float32),
        camera=camera,
        metrics=metrics,
        loss_curve=curve,
    )
