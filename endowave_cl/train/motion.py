"""Moving initial Gaussians: per-pixel velocities from the pseudo ground-truth flow, and the 4D
Gaussian (log scales, left / right quaternions) of a point that moves at a given velocity.

Why: a 4D Gaussian moves at Sigma_xt / Sigma_tt.  Started still (identity rotations), it must learn
that velocity by rotating in the x-t planes, and with space in scene units and time in [0, 1] the
needed rotation is large (tan(angle) ~ speed in scene units per unit time: 20-30 on the synthetic
scenes), so in practice the Gaussians cross-fade instead of moving.  The flow is known before the
first step, so every initial Gaussian is given the velocity of the tissue under its pixel.

A point at x0 + v (t - mu_t) with spatial std s around that line, alive with temporal std sigma_t,
is the 4D Gaussian

    Sigma = [[s^2 I + sigma_t^2 v v^T,  sigma_t^2 v],
             [sigma_t^2 v^T,            sigma_t^2  ]]

whose conditional at any t has mean x0 + v (t - mu_t), covariance s^2 I and marginal std sigma_t.
``gaussian_from_covariance`` factors such a Sigma into R diag(exp(2 log_scale)) R^T and R into the
quaternion pair of reference/project.py's convention (R = M_left(q_l) M_right(q_r)).
"""
from __future__ import annotations

import math
from typing import Dict, Tuple

import cv2
import numpy as np

from ..gaussians import quat_left as _quat_left, quat_right as _quat_right

# Flow is trusted where its forward-backward check passed; elsewhere the velocity is filled in
# from valid neighbours by normalised convolution with a Gaussian of this std (fraction of the
# image diagonal); where too little valid flow is near, the velocity is 0.
FILL_SIGMA = 0.03
FILL_MIN_WEIGHT = 0.05


# The 16 products M_left(e_k) M_right(e_l) of basis quaternions are signed permutation matrices,
# orthogonal under the Frobenius product with squared norm 4: they are a basis of 4 x 4 matrices,
# and R = M_left(a) M_right(b) has coordinates a_k b_l in it.
_EYE = np.eye(4)
_BASIS = np.einsum("kij,ljm->klim", _quat_left(_EYE), _quat_right(_EYE))   # [4, 4, 4, 4]


def rotation_to_quats(R: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """[N, 4, 4] rotations (det +1) -> unit quaternions q_l, q_r [N, 4] with
    M_left(q_l) M_right(q_r) = R (the pair is unique up to a common sign)."""
    R = np.asarray(R, np.float64)
    A = np.einsum("nim,klim->nkl", R, _BASIS) / 4.0       # [N, 4, 4] = outer(q_l, q_r)
    row = np.argmax(np.linalg.norm(A, axis=2), axis=1)    # best-conditioned row of the rank-1 A
    b = A[np.arange(len(A)), row]                         # [N, 4] ~ q_l[row] * q_r
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    a = np.einsum("nkl,nl->nk", A, b)                      # [N, 4] = q_l
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    return a, b


def gaussian_from_covariance(sigma: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """[N, 4, 4] SPD covariances -> (log scales [N, 4], q_l [N, 4], q_r [N, 4]).

    The principal axis with the largest time component goes to slot 3 (the "time" scale that the
    density control treats as such); the other three keep ascending order.
    """
    lam, V = np.linalg.eigh(np.asarray(sigma, np.float64))           # ascending, columns
    t_axis = np.argmax(np.abs(V[:, 3, :]), axis=1)                  # [N]
    order = np.array([[j for j in range(4) if j != i] + [i] for i in range(4)])[t_axis]   # [N, 4]
    lam = np.take_along_axis(lam, order, 1)
    V = np.take_along_axis(V, order[:, None, :], 2)
    flip = np.linalg.det(V) < 0
    V[flip, :, 0] *= -1.0                                           # a proper rotation
    q_l, q_r = rotation_to_quats(V)
    return 0.5 * np.log(np.maximum(lam, 1e-30)), q_l, q_r


def moving_covariance(spatial, sigma_t: np.ndarray, velocity: np.ndarray) -> np.ndarray:
    """Conditional spatial covariance [N, 3, 3] (or an isotropic std [N]), temporal std [N] and
    velocity [N, 3] -> the 4D Sigma [N, 4, 4] of the module docstring."""
    spatial = np.asarray(spatial, np.float64)
    cond = spatial[:, None, None] ** 2 * np.eye(3) if spatial.ndim == 1 else spatial
    st2 = np.broadcast_to(np.asarray(sigma_t, np.float64) ** 2, cond.shape[:1])
    v = np.asarray(velocity, np.float64)
    S = np.zeros((len(cond), 4, 4))
    S[:, :3, :3] = cond + st2[:, None, None] * v[:, :, None] * v[:, None, :]
    S[:, :3, 3] = S[:, 3, :3] = st2[:, None] * v
    S[:, 3, 3] = st2
    return S


def motion_of(sigma: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The inverse of ``moving_covariance``: Sigma [N, 4, 4] -> (conditional spatial covariance
    [N, 3, 3], temporal std [N], velocity [N, 3])."""
    sigma = np.asarray(sigma, np.float64)
    stt = np.maximum(sigma[:, 3, 3], 1e-30)
    v = sigma[:, :3, 3] / stt[:, None]
    cond = sigma[:, :3, :3] - stt[:, None, None] * v[:, :, None] * v[:, None, :]
    return cond, np.sqrt(stt), v


def temporal_coverage(mu_t: np.ndarray, sigma_t: np.ndarray) -> np.ndarray:
    """[N] the integral over the sequence's time [0, 1] of each Gaussian's temporal marginal
    exp(-(t - mu_t)^2 / (2 sigma_t^2)): the fraction of the sequence it is alive for
    (sqrt(2 pi) sigma_t for a short-lived one well inside the sequence, at most 1)."""
    mu = np.asarray(mu_t, np.float64)
    s = np.maximum(np.asarray(sigma_t, np.float64), 1e-12) * math.sqrt(2.0)
    erf = np.frompyfunc(math.erf, 1, 1)
    return (math.sqrt(math.pi) / 2.0 * s * (erf((1.0 - mu) / s) - erf(-mu / s))).astype(np.float64)


def spatial_size(sigma: np.ndarray) -> np.ndarray:
    """[N, 4, 4] -> [N]: the largest std of the Gaussian in space at any one time (the same at
    every t): what density control compares with the scene extent."""
    cond = motion_of(sigma)[0]
    return np.sqrt(np.maximum(np.linalg.eigvalsh(cond)[:, -1], 0.0))


def _fill(values: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Normalised convolution: values [H, W, C] known where weight [H, W] > 0 -> filled [H, W, C]
    (0 where too little is known nearby)."""
    H, W = weight.shape
    sigma = max(1.0, FILL_SIGMA * float(np.hypot(H, W)))
    ksize = int(2 * round(3 * sigma) + 1)
    w = cv2.GaussianBlur(weight.astype(np.float32), (ksize, ksize), sigma, borderType=cv2.BORDER_CONSTANT)
    out = np.empty_like(values, dtype=np.float32)
    for c in range(values.shape[2]):
        out[..., c] = cv2.GaussianBlur((values[..., c] * weight).astype(np.float32), (ksize, ksize), sigma,
                                       borderType=cv2.BORDER_CONSTANT)
    known = weight > 0
    out = np.where(known[..., None], values, out / np.maximum(w, 1e-12)[..., None])
    return np.where((known | (w >= FILL_MIN_WEIGHT))[..., None], out, 0.0).astype(np.float32)


def _lift(frame, depth: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Pixels (u, v) [P] (centres already added) at depths [P] -> world points [P, 3]."""
    cam = frame.camera
    pc = np.stack([(u - cam.cx) / cam.fx * depth, (v - cam.cy) / cam.fy * depth, depth, np.ones_like(depth)], 1)
    return (pc @ np.linalg.inv(cam.viewmat.astype(np.float64)).T)[:, :3]


def _displacement(frames, k: int, k2: int, flow: np.ndarray, valid: np.ndarray, depth_k: np.ndarray,
                  depth_prior: float) -> Tuple[np.ndarray, np.ndarray]:
    """World displacement [H, W, 3] per unit time of frame k's pixels towards frame k2 along the
    flow, and where it is trusted [H, W].  The depth change comes from k2's depth map where both
    frames have depth there; otherwise the point keeps its depth."""
    H, W = flow.shape[:2]
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    u0, v0 = u + 0.5, v + 0.5
    u1, v1 = u0 + flow[..., 0], v0 + flow[..., 1]
    z0 = depth_k
    z1 = z0.copy()
    d2 = frames[k2].depth
    if d2 is not None and frames[k].depth is not None:
        iu = np.clip(np.floor(u1).astype(int), 0, W - 1)
        iv = np.clip(np.floor(v1).astype(int), 0, H - 1)
        zz = np.asarray(d2, np.float64)[iv, iu]
        z1 = np.where((zz > 0) & (z0 > 0), zz, z0)
    p0 = _lift(frames[k], z0.reshape(-1), u0.reshape(-1), v0.reshape(-1))
    p1 = _lift(frames[k2], z1.reshape(-1), u1.reshape(-1), v1.reshape(-1))
    dt = float(frames[k2].time - frames[k].time)
    ok = (np.asarray(valid) > 0.5) & (z0 > 0)
    return ((p1 - p0) / dt).reshape(H, W, 3), ok


def frame_velocities(frames, train_indices, flows: Dict[int, object], depth_prior: float
                     ) -> Dict[int, Tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """{k: (velocity [H, W, 3], trusted [H, W] bool, acceleration [H, W])}: world velocity (scene
    units per unit time) of every training frame's pixels, the mean of the forward estimate (flow
    k -> next training frame) and the backward one (the previous pair's backward flow k -> previous
    frame) where each is trusted, filled in smoothly where neither is (``_fill``); ``trusted`` marks
    the pixels where at least one estimate passed its consistency check; ``acceleration`` is the
    change between the two estimates per unit time (scene units per unit time squared) where both
    are trusted, NaN elsewhere (the motion's curvature is unknown there).  Frames with no flow pair
    get no entry."""
    by_dst = {p.dst: p for p in flows.values()}
    out = {}
    for k in train_indices:
        fr = frames[k]
        H, W = fr.image.shape[:2]
        depth = (np.full((H, W), depth_prior) if fr.depth is None else np.asarray(fr.depth, np.float64))
        acc = np.zeros((H, W, 3))
        wsum = np.zeros((H, W))
        est = []                    # (velocity, trusted, time to the other frame) per direction
        if k in flows:
            p = flows[k]
            d, ok = _displacement(frames, k, p.dst, p.flow, p.valid, depth, depth_prior)
            est.append((d, ok, abs(float(frames[p.dst].time - fr.time))))
        if k in by_dst:
            p = by_dst[k]
            d, ok = _displacement(frames, k, p.src, p.flow_bw, p.valid_bw, depth, depth_prior)
            est.append((d, ok, abs(float(frames[p.src].time - fr.time))))
        for d, ok, _ in est:
            acc += np.where(ok[..., None], d, 0.0)
            wsum += ok
        if not wsum.any():
            continue
        accel = np.full((H, W), np.nan)
        if len(est) == 2:
            (d0, ok0, dt0), (d1, ok1, dt1) = est
            both = ok0 & ok1
            # forward estimate ~ v + a dt0 / 2, backward ~ v - a dt1 / 2 (secant slopes)
            a = np.linalg.norm(d0 - d1, axis=-1) / max(0.5 * (dt0 + dt1), 1e-12)
            accel[both] = a[both]
        out[k] = (_fill(acc / np.maximum(wsum, 1)[..., None], (wsum > 0).astype(np.float32)), wsum > 0, accel)
    return out


def linear_lifetime(size: np.ndarray, accel: np.ndarray, floor: float, cap: float) -> np.ndarray:
    """Temporal std [N] for Gaussians of spatial std ``size`` [N] moving with acceleration
    ``accel`` [N] (NaN: unknown): how long a constant velocity stays within one spatial std of the
    true path, 0.5 |a| dt^2 <= size, clipped to [floor, cap]; unknown curvature gets the floor."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.sqrt(2.0 * np.asarray(size, np.float64) / np.asarray(accel, np.float64))
    t = np.where(np.isfinite(t), t, np.where(np.isnan(accel), floor, cap))
    return np.clip(t, floor, max(floor, cap))
