"""Export the 4D model at one time t as a standard 3DGS PLY (viewable in any 3DGS viewer).

Per Gaussian (4D -> 3D at time t, docs/ARCHITECTURE.md conventions):
- centre: the conditional mean mu_x|t; covariance: the conditional Sigma_x|t, written as
  3DGS's scale (log std along the eigenvectors) and rotation quaternion (w, x, y, z) of the
  eigenvector matrix, made a proper rotation (det +1) by flipping one eigenvector if needed;
- opacity: logit(sigmoid(opacity) * m), m = exp(-0.5 (t - mu_t)^2 / Sigma_tt) the marginal;
  Gaussians with m < MARGINAL_CULL (0.05) are dropped, as the renderer skips them;
- colour: the SH coefficients at t, c_k = sum_n c[n, k] cos(omega_n t + phi_n) (phi_0 unused,
  gaussians.py), as f_dc_0..2 = c_0 and f_rest_0..44 channel-major (f_rest[ch * 15 + k - 1]),
  zero-padded when the model's SH degree is below 3; normals are 0.
Binary little-endian, float32, written atomically.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .atomic import atomic_open
from .gaussians import MARGINAL_CULL, TEASH_PERIOD, Gaussians, covariance_4d

PLY_SH_REST = 15        # 3DGS PLY files carry degree-3 SH: 15 non-DC coefficients per channel
MIN_STD = 1e-12         # eigenvalues are clamped so that log(std) stays finite
OPACITY_CLAMP = 1e-7    # effective opacity is clamped to [1e-7, 1 - 1e-7] before the logit


def ply_property_names() -> list:
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * PLY_SH_REST)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Proper rotations [N, 3, 3] -> unit quaternions (w, x, y, z) [N, 4] (3DGS's build_rotation inverse).

    Shepperd's method: of 4w^2, 4x^2, 4y^2, 4z^2 take the largest for the square root (well
    conditioned), and the other components from the off-diagonal sums / differences.
    """
    r = np.asarray(R, np.float64)
    tr = np.trace(r, axis1=1, axis2=2)
    d0, d1, d2 = r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]
    a21, a12 = r[:, 2, 1], r[:, 1, 2]
    a02, a20 = r[:, 0, 2], r[:, 2, 0]
    a10, a01 = r[:, 1, 0], r[:, 0, 1]
    k = np.argmax(np.stack([tr, d0, d1, d2], 1), 1)                          # [N]
    s = 2 * np.sqrt(np.maximum(1.0 + np.choose(k, [tr, d0 - d1 - d2, d1 - d0 - d2, d2 - d0 - d1]), 1e-300))
    branches = [np.stack([0.25 * s, (a21 - a12) / s, (a02 - a20) / s, (a10 - a01) / s], 1),
                np.stack([(a21 - a12) / s, 0.25 * s, (a01 + a10) / s, (a02 + a20) / s], 1),
                np.stack([(a02 - a20) / s, (a01 + a10) / s, 0.25 * s, (a12 + a21) / s], 1),
                np.stack([(a10 - a01) / s, (a02 + a20) / s, (a12 + a21) / s, 0.25 * s], 1)]
    q = np.choose(k[:, None], branches)                                      # [N, 4]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def gaussians_at(g: Gaussians, t: float) -> dict:
    """The 3D Gaussians at time t as float64 arrays (see the module docstring)."""
    sigma = covariance_4d(g)                                   # [N, 4, 4]
    sxx, sxt, stt = sigma[:, :3, :3], sigma[:, :3, 3], sigma[:, 3, 3]
    dt = t - g.means[:, 3].astype(np.float64)                  # [N]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        m = np.exp(-0.5 * dt * dt / stt)                       # [N]
        mean = g.means[:, :3].astype(np.float64) + sxt * (dt / stt)[:, None]
        cov = sxx - sxt[:, :, None] * sxt[:, None, :] / stt[:, None, None]
    keep = np.isfinite(m) & (m >= MARGINAL_CULL) & np.all(np.isfinite(cov), axis=(1, 2))
    mean, cov, m = mean[keep], cov[keep], m[keep]
    evals, evecs = np.linalg.eigh(0.5 * (cov + np.swapaxes(cov, 1, 2)))   # [M, 3], [M, 3, 3] columns
    flip = np.linalg.det(evecs) < 0
    evecs[flip, :, 2] *= -1                                    # det +1: a proper rotation
    std = np.sqrt(np.maximum(evals, MIN_STD ** 2))
    opac = 1.0 / (1.0 + np.exp(-g.opacity[keep].astype(np.float64))) * m
    nt1 = g.sh.shape[1]
    omega = 2.0 * math.pi * np.arange(nt1) / TEASH_PERIOD      # [NT+1]
    cosn = np.cos(omega[None, :] * t + g.phase[keep].astype(np.float64))
    cosn[:, 0] = 1.0                                           # phi_0 unused
    sh_t = np.einsum("nikc,ni->nkc", g.sh[keep].astype(np.float64), cosn)   # [M, K, 3]
    return {"mean": mean, "cov": cov, "std": std, "rot": evecs, "opacity": opac, "sh": sh_t, "keep": keep}


def export_ply(path, g: Gaussians, t: float, scale: float = 1.0) -> int:
    """Write the model at time t to ``path``; returns the number of Gaussians written.  scale:
    positions and sizes are multiplied by it (1 / the run's world_scale writes the scene files'
    own units, data/scene.py)."""
    path = Path(path)
    a = gaussians_at(g, float(t))
    a["mean"] = a["mean"] * float(scale)
    a["std"] = a["std"] * float(scale)
    M = a["mean"].shape[0]
    K = a["sh"].shape[1]
    if K - 1 > PLY_SH_REST:
        raise ValueError(f"export_ply: SH degree above 3 ({K} bases) does not fit the 3DGS PLY layout")
    rest = np.zeros((M, 3, PLY_SH_REST))
    rest[:, :, : K - 1] = np.transpose(a["sh"][:, 1:, :], (0, 2, 1))   # channel-major
    p = np.clip(a["opacity"], OPACITY_CLAMP, 1 - OPACITY_CLAMP)
    cols = [a["mean"], np.zeros((M, 3)), a["sh"][:, 0, :], rest.reshape(M, 3 * PLY_SH_REST),
            np.log(p / (1 - p))[:, None], np.log(a["std"]), matrix_to_quaternion(a["rot"])]
    data = np.concatenate(cols, 1).astype("<f4")               # [M, 62]
    names = ply_property_names()
    assert data.shape[1] == len(names)
    header = "ply\nformat binary_little_endian 1.0\n"
    header += f"comment endowave-cl export at t = {float(t)!r}\n"
    header += f"element vertex {M}\n" + "".join(f"property float {n}\n" for n in names) + "end_header\n"
    with atomic_open(path) as f:
        f.write(header.encode("ascii"))
        f.write(np.ascontiguousarray(data).tobytes())
    return M
