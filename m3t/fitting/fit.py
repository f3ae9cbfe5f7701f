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

- ``lbfgs``: L-BFGS with a strong-Wolfe line search and a convergence test (:func:`_minimise`);
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
from m3t.fitting.lbfgs import lbfgs_rounds, minimise_batched
from m3t.fitting.lockstep import minimise_rows
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


class _Pack:
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


class _Terms:
    """The objective's three terms per clip, (C,) each; for one clip exactly :func:`reprojection_loss`,
    :func:`acceleration_loss` and the mean over streams of the mean squared distance to the initialisation."""

    def __init__(self, pack: _Pack, conf: torch.Tensor, parts: list[slice], valid: torch.Tensor):
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


def _minimise(loss_fn, variables: list[torch.Tensor], cfg: FittingConfig, stage: str, lr: float,
              curve: list[float], project_bounds=None) -> None:
    """Minimise ``loss_fn()`` over ``variables`` in place, appending every objective evaluation to ``curve``.

    The budget is ``iterations`` objective (and gradient) evaluations, ``camera_iterations`` for the camera
    stage. ``adam``: that many Adam steps at ``lr`` with a cosine decay to 5 %, the bounds projected after each
    step. ``lbfgs``: L-BFGS with a strong-Wolfe line search (``lr`` unused), in rounds of ``lbfgs_round``
    iterations, at most that many evaluations; it stops early once a round improved the loss by less than
    ``tolerance`` (relative). Bounded variables enter ``loss_fn`` clamped and are projected onto their bounds
    after every round.
    """
    iterations = cfg.camera_iterations if stage == "camera" else cfg.iterations
    if cfg.solver == "adam":
        opt = torch.optim.Adam(variables, lr=lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(1, iterations), eta_min=lr * 0.05)
        for _ in range(iterations):
            opt.zero_grad()
            loss = loss_fn()
            loss.backward()
            opt.step()
            sched.step()
            if project_bounds is not None:
                project_bounds()
            curve.append(float(loss.detach()))
        return
    if cfg.solver != "lbfgs":
        raise ValueError(f"fitting.solver is {cfg.solver!r}; expected 'lbfgs' or 'adam'")

    def evaluate(opt: torch.optim.Optimizer) -> torch.Tensor:
        opt.zero_grad()
        loss = loss_fn()
        loss.backward()
        return loss

    curve.extend(lbfgs_rounds(variables, evaluate, iterations, cfg.lbfgs_round, cfg.lbfgs_history, cfg.tolerance,
                              project_bounds))


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
    pack = _Pack([t.num_frames for t in tracks], device)
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
    terms = _Terms(pack, conf, parts, valid)

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

    def solve(loss_per_clip, names: list[str], stage: str, lr: float, curve: list[float],
              project_bounds=None) -> None:
        """Minimise the clips' summed objective over ``opt[names]``; lbfgs_batched / lbfgs_lockstep: each clip
        its own."""
        if not cfg.per_clip_problems:
            _minimise(lambda: loss_per_clip().sum(), [opt[k] for k in names], cfg, stage, lr, curve, project_bounds)
            return
        per_clip = [k for k in names if k in ("identity", "cam_rot", "cam_trans")]
        per_row = [k for k in names if k not in per_clip]
        budget = cfg.camera_iterations if stage == "camera" else cfg.iterations
        if cfg.solver == "lbfgs_batched":
            curves = minimise_batched(opt, per_row, per_clip, pack.slices, loss_per_clip, budget, cfg.lbfgs_round,
                                      cfg.lbfgs_history, cfg.tolerance, bounds if project_bounds else None)
        else:
            curves = minimise_rows(opt, per_row, per_clip, pack.clip, loss_per_clip, budget, cfg.lbfgs_round,
                                   cfg.tolerance, cfg.lbfgs_history, project_bounds)
        if stage == "full":
            clip_curves.extend(curves)

    clip_curves: list[list[float]] = []  # lbfgs_lockstep: each clip's own curve of the full stage
    curve: list[float] = []
    # Stage 1: camera only, against the torso and head (arms and hands are far from the rest pose).
    torso_conf = torch.zeros_like(conf)
    torso_conf[:, parts[0]] = conf[:, parts[0]]
    torso_conf[:, parts[0].start + 13: parts[0].start + 23] = 0.0  # elbows, wrists and hand points of the pose part
    if float(torso_conf.sum()) > 0:
        torso = _Terms(pack, torso_conf, [parts[0]], valid)
        with torch.no_grad():
            rest_points = body.forward_keypoints(current_params(), current_identity(), kpset, **shape)
        solve(lambda: torso.reprojection(uv_of(rest_points), target), ["cam_rot", "cam_trans"], "camera",
              cfg.lr * 2, [])

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
    solve(full_loss, names, "full", cfg.lr, curve, project_bounds=bounded)

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
