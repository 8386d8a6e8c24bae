"""Initial 4D Gaussians from the training frames (host, numpy).

With depth: every supervised pixel (depth > 0 and mask = 1) of every training frame is
back-projected through its pixel centre (u + 0.5, v + 0.5) to world space at its depth, at the
frame's time (mu_t = frame time); a uniform random subset of max_points of these is kept.

Without depth (a frame whose depth is None): the same with a constant depth D: a fronto-parallel
surface covering the view.  D is the median of the valid depths of the other training frames when
some have depth, else sqrt(near * far), the midpoint of the bounds in log-depth (scale-free: the
bounds of endoscopic scenes span orders of magnitude, e.g. [0.03, 250] for StereoMIS, where the
arithmetic midpoint would sit far behind the tissue); a near bound of 0 is replaced by far / 1000
(data/scene.py prior_plane_depth; the loader's scene units put that plane at SCENE_DEPTH).  Seen
from the training camera such a surface reproduces the frame exactly; training then moves it.

Per Gaussian:
- colour: TEASH DC term sh[:, 0, 0, :] = (rgb - 0.5) / SH_C0 of its pixel, every other term 0;
- spatial scales (isotropic): the pixel footprint at its depth, depth * (1/fx + 1/fy) / 2, times
  the subsampling stride: the mean spacing, in pixels, of the Gaussians seen at one time (those
  whose marginal weight is above one half there), so that neighbours overlap without piling up;
- time scale: TIME_SCALE_FRAMES x the spacing of the training frame times, so a Gaussian lives
  for a few frames (the marginal exp(-0.5 dt^2 / s_t^2) is 0.6 one frame spacing, 0.14 two
  spacings away, and below the 0.05 cull 2.45 s_t ~ 5 spacings away);
- rotations identity (q_l = q_r = (1, 0, 0, 0)), opacity logit(INIT_OPACITY), phases 0.
"""
from __future__ import annotations

import math
from typing import Mapping, Optional, Sequence

import numpy as np

from ..data.scene import prior_plane_depth
from ..errors import EndowaveError
from ..gaussians import Gaussians, num_sh_bases
from .motion import frame_velocities, gaussian_from_covariance, linear_lifetime, moving_covariance

SH_C0 = 0.28209479177387814   # Y_00: DC coefficient c gives colour 0.5 + SH_C0 * c
INIT_OPACITY = 0.1
TIME_SCALE_FRAMES = 2.0       # time std in units of the training frame spacing
UNTRUSTED_TIME_SCALE_FRAMES = 1.0   # time std where the flow is not trusted (init_gaussians)
VISIBLE_WITHIN = 1.18         # |t - mu_t| < 1.18 sigma_t: marginal weight above one half
MASK_THRESHOLD = 0.5          # mask values are 0 / 1; anything above 0.5 is supervised tissue


def _frame_spacing(times: np.ndarray) -> float:
    """Median spacing of the distinct training times (1 when there is a single time)."""
    u = np.unique(times)
    return float(np.median(np.diff(u))) if u.size > 1 else 1.0


def _stride(point_times: np.ndarray, times: np.ndarray, n_keep: int, total: int, n_frames: int,
            sigma) -> float:
    """Mean spacing, in pixels (>= 1), of the kept points seen at one time: a point is seen at t
    when its marginal weight there is above one half (|t - mu_t| < VISIBLE_WITHIN sigma_t)."""
    sig = np.broadcast_to(np.asarray(sigma, np.float64), point_times.shape)
    visible = np.mean([np.mean(np.abs(point_times - t) <= VISIBLE_WITHIN * sig) for t in times])
    return max(1.0, math.sqrt(total / n_frames / max(1.0, n_keep * visible)))


def prior_depth(frames, train_indices: Sequence[int], near: float, far: float) -> float:
    """Depth of the fronto-parallel prior (module docstring)."""
    vals = [np.asarray(frames[k].depth, np.float64) for k in train_indices if frames[k].depth is not None]
    vals = [v[v > 0] for v in vals]
    vals = [v for v in vals if v.size]
    if vals:
        return float(np.median(np.concatenate(vals)))
    if not (far > 0 and near >= 0):
        raise EndowaveError(f"init: the depth bounds must satisfy 0 <= near, 0 < far to place the initial "
                            f"surface (near {near}, far {far})")
    return prior_plane_depth(near, far)


def _valid_pixels(frame, default_depth: float) -> tuple:
    """(flat indices [P] of supervised pixels, depth map [H, W]) of one frame."""
    H, W = frame.image.shape[:2]
    depth = (np.full((H, W), default_depth, np.float64) if frame.depth is None
             else np.asarray(frame.depth, np.float64))
    ok = depth > 0
    if frame.mask is not None:
        ok &= np.asarray(frame.mask) > MASK_THRESHOLD
    return np.flatnonzero(ok.reshape(-1)), depth


def init_gaussians(frames, train_indices: Sequence[int], near: float, far: float, max_points: int,
                   seed: int = 0, sh_degree: int = 3, nt: int = 2, time_scale: float = 0.0,
                   flows: Optional[Mapping[int, object]] = None) -> Gaussians:
    """Initial Gaussians (module docstring); frames[k] has image, depth, mask, camera, time.

    flows: the pseudo ground-truth flow of the training pairs (``data.flow.flow_for_scene``); when
    given, every Gaussian starts moving with the tissue under its pixel (train/motion.py)."""
    idx = [int(k) for k in train_indices]
    if not idx:
        raise EndowaveError("init: no training frames")
    if max_points < 1:
        raise EndowaveError(f"init: max_points must be at least 1, got {max_points}")
    d_prior = prior_depth(frames, idx, near, far) if any(frames[k].depth is None for k in idx) else 0.0
    valid = [_valid_pixels(frames[k], d_prior) for k in idx]
    counts = np.array([v[0].size for v in valid], np.int64)   # [F]
    total = int(counts.sum())
    if total == 0:
        if all(frames[k].depth is None for k in idx):   # no depth used: only the masks can be at fault
            raise EndowaveError("init: no training pixel is tissue (every mask pixel is tool)")
        raise EndowaveError("init: no training pixel has a valid depth inside the tissue mask")
    rng = np.random.default_rng(seed)
    n_keep = min(int(max_points), total)
    chosen = np.sort(rng.choice(total, size=n_keep, replace=False)) if n_keep < total else np.arange(total)
    times = np.array([frames[k].time for k in idx], np.float64)                # [F]
    sigma_t = time_scale if time_scale > 0 else TIME_SCALE_FRAMES * _frame_spacing(times)
    starts = np.concatenate([[0], np.cumsum(counts)])

    vel_maps = {}
    if flows:
        vel_maps = frame_velocities(frames, idx, flows, d_prior if d_prior > 0 else
                                    prior_depth(frames, idx, near, far))
    xyz, rgb, tt, size, vel, trusted, accel = [], [], [], [], [], [], []
    for f_i, k in enumerate(idx):
        lo, hi = np.searchsorted(chosen, [starts[f_i], starts[f_i + 1]])
        if hi == lo:
            continue
        fr = frames[k]
        flat = valid[f_i][0][chosen[lo:hi] - starts[f_i]]      # [P_f] flat pixel indices
        depth = valid[f_i][1].reshape(-1)[flat]                # [P_f]
        W = fr.image.shape[1]
        v, u = np.divmod(flat, W)
        cam = fr.camera
        x = (u + 0.5 - cam.cx) / cam.fx * depth
        y = (v + 0.5 - cam.cy) / cam.fy * depth
        pc = np.stack([x, y, depth, np.ones_like(depth)], 1)  # [P_f, 4] camera space
        pw = pc @ np.linalg.inv(cam.viewmat.astype(np.float64)).T
        xyz.append(pw[:, :3])
        rgb.append(np.asarray(fr.image, np.float64).reshape(-1, 3)[flat])
        tt.append(np.full(depth.shape, float(fr.time)))
        size.append(depth * 0.5 * (1.0 / cam.fx + 1.0 / cam.fy))        # one pixel; x stride below
        vm = vel_maps.get(k)
        vel.append(np.zeros((flat.size, 3)) if vm is None else vm[0].reshape(-1, 3)[flat].astype(np.float64))
        trusted.append(np.ones(flat.size, bool) if vm is None else vm[1].reshape(-1)[flat])
        accel.append(np.full(flat.size, np.nan) if vm is None else vm[2].reshape(-1)[flat])
    xyz, rgb, tt, size, vel, trusted, accel = (np.concatenate(a) for a in (xyz, rgb, tt, size, vel, trusted, accel))
    spacing = _frame_spacing(times)
    if vel_maps:
        # A Gaussian lives as long as its constant velocity follows the tissue (motion.linear_lifetime),
        # between TIME_SCALE_FRAMES spacings and sigma_t; where the flow failed its consistency check
        # (fast tools, occlusions, highlights) the motion is unknown and it lives for a frame or so,
        # so that it cannot smear what it shows across the sequence.
        floor = min(sigma_t, TIME_SCALE_FRAMES * spacing)
        sigma_pt = linear_lifetime(size * _stride(tt, times, n_keep, total, len(idx), sigma_t),
                                   accel, floor, sigma_t)
        sigma_pt = np.where(trusted, sigma_pt, min(sigma_t, UNTRUSTED_TIME_SCALE_FRAMES * spacing))
    else:
        sigma_pt = np.full(len(tt), sigma_t)
    # The kept points of every frame whose lifetime covers t overlap at time t: size the Gaussians by
    # the spacing of those seen at once.
    size = size * _stride(tt, times, n_keep, total, len(idx), sigma_pt)
    N = xyz.shape[0]
    K = num_sh_bases(sh_degree)
    sh = np.zeros((N, nt + 1, K, 3), np.float32)
    sh[:, 0, 0, :] = (rgb - 0.5) / SH_C0
    scales = np.empty((N, 4), np.float64)
    scales[:, :3] = np.log(np.maximum(size, 1e-12))[:, None]
    scales[:, 3] = np.log(sigma_pt)
    quat_l = np.zeros((N, 4))
    quat_l[:, 0] = 1.0
    quat_r = quat_l.copy()
    moving = np.flatnonzero(np.abs(vel).max(1) > 0)
    if moving.size:
        cov = moving_covariance(np.maximum(size[moving], 1e-12), sigma_pt[moving], vel[moving])
        scales[moving], quat_l[moving], quat_r[moving] = gaussian_from_covariance(cov)
    return Gaussians(means=np.concatenate([xyz, tt[:, None]], 1), scales=scales, quat_l=quat_l, quat_r=quat_r,
                     opacity=np.full(N, math.log(INIT_OPACITY / (1 - INIT_OPACITY))),
                     sh=sh, phase=np.zeros((N, nt + 1)))
