"""The 4D Gaussian parameter set and its fixed memory layout.

Every kernel and reference uses this layout (float32, C order):

    means     [N, 4]          (x, y, z, t): 4D mean, world units and normalised time in [0, 1]
    scales    [N, 4]          log of the standard deviations along the 4 principal axes (x, y, z, t)
    quat_l    [N, 4]          left unit quaternion (w, x, y, z), stored unnormalised
    quat_r    [N, 4]          right unit quaternion (w, x, y, z), stored unnormalised
    opacity   [N]             logit of the opacity
    sh        [N, NT+1, K, 3] TEASH coefficients c[n, k, rgb]; K = (L+1)^2 SH bases, n = 0..NT
    phase     [N, NT+1]       learnable phase phi_n of each temporal frequency (phi_0 unused)

TEASH colour (chosen convention, docs/METHOD.md): tau = t (global time, as the paper writes),
omega_n = 2 pi n / TEASH_PERIOD with TEASH_PERIOD = 2 (twice the normalised sequence length,
so the first harmonic is not forced to repeat between the first and the last frame);
colour = max(0, 0.5 + sum_{n,k} c[n,k] Y_k(d) cos(omega_n t + phi_n)), d the unit direction from
the camera centre to the conditional mean at t.  phi_0 is unused: cos(0 * t + phi_0) is taken as 1.

The model layer (numpy, torch-free): the 4D rotation and covariance of every Gaussian in the
convention of reference/project.py (R = M_left(q_l) M_right(q_r)), used by density control,
export and the viewer; checkpoint files are read and written by endowave_cl/checkpoint.py.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Dict

import numpy as np
import pyopencl.array as cla

SH_DEGREE = 3          # L: spherical-harmonic degree (K = 16 bases)
TEMPORAL_FREQS = 2     # NT: temporal frequencies n = 1..NT besides the constant n = 0
TEASH_PERIOD = 2.0     # T in omega_n = 2 pi n / T, in normalised time units
MARGINAL_CULL = 0.05   # a Gaussian whose marginal temporal weight is below this is skipped
LOWPASS = 0.1          # px^2 added to the diagonal of every projected 2D covariance: the smallest
                       # footprint a Gaussian can have (3DGS adds 0.3; 0.1 fits the frames closer
                       # and renders the unseen ones sharper on the validation frames of every
                       # shared scene, research/QUALITY.md finding 40).  A checkpoint records the
                       # model's layout, and one trained with another value renders differently:
                       # checkpoint.CHECKPOINT_FORMAT changes with it

# Real spherical harmonics (3DGS constants and sign convention), degree 0..3; the kernels
# (cl/project4d_common.h) hold the same values.
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
         -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)



def sh_basis_terms(x, y, z, degree: int) -> list:
    """The real SH basis values of unit directions (x, y, z), each [N], degree 0..3, 3DGS order and
    signs: a list of (degree+1)^2 arrays.  Plain arithmetic only, so numpy arrays and torch tensors
    (the autograd reference, reference/project.py) both work; callers stack the list."""
    out = [x * 0.0 + SH_C0]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2 * zz - xx - yy),
                SH_C2[3] * x * z, SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * x * y * z,
                SH_C3[2] * y * (4 * zz - xx - yy), SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
                SH_C3[4] * x * (4 * zz - xx - yy), SH_C3[5] * z * (xx - yy),
                SH_C3[6] * x * (xx - 3 * yy)]
    return out


PARAM_NAMES = ("means", "scales", "quat_l", "quat_r", "opacity", "sh", "phase")


def num_sh_bases(degree: int = SH_DEGREE) -> int:
    return (degree + 1) ** 2


@dataclass
class Gaussians:
    """Host (numpy) copy of the parameters; see the module docstring for the layout."""
    means: np.ndarray    # [N, 4]
    scales: np.ndarray   # [N, 4]
    quat_l: np.ndarray   # [N, 4]
    quat_r: np.ndarray   # [N, 4]
    opacity: np.ndarray  # [N]
    sh: np.ndarray       # [N, NT+1, K, 3]
    phase: np.ndarray    # [N, NT+1]

    def __post_init__(self):
        for f in fields(self):
            setattr(self, f.name, np.ascontiguousarray(getattr(self, f.name), dtype=np.float32))

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return int(round(np.sqrt(self.sh.shape[2]))) - 1

    @property
    def temporal_freqs(self) -> int:
        return int(self.sh.shape[1]) - 1

    def as_dict(self) -> Dict[str, np.ndarray]:
        return {n: getattr(self, n) for n in PARAM_NAMES}

    def take(self, rows: np.ndarray) -> "Gaussians":
        """The Gaussians of the given rows (indices or a boolean mask), in that order."""
        return Gaussians(**{n: getattr(self, n)[rows] for n in PARAM_NAMES})

    @classmethod
    def empty(cls, degree: int = SH_DEGREE, nt: int = TEMPORAL_FREQS) -> "Gaussians":
        K = num_sh_bases(degree)
        return cls(np.zeros((0, 4)), np.zeros((0, 4)), np.zeros((0, 4)), np.zeros((0, 4)),
                   np.zeros((0,)), np.zeros((0, nt + 1, K, 3)), np.zeros((0, nt + 1)))

    @classmethod
    def random(cls, n: int, seed: int = 0, degree: int = SH_DEGREE, nt: int = TEMPORAL_FREQS,
               center=(0.0, 0.0, 3.0), spread=1.0, scale=0.05) -> "Gaussians":
        """Random Gaussians in front of an identity camera; for tests and benchmarks."""
        rng = np.random.default_rng(seed)
        K = num_sh_bases(degree)
        means = np.concatenate([np.asarray(center) + spread * rng.uniform(-1, 1, (n, 3)),
                                rng.uniform(0, 1, (n, 1))], 1)
        scales = np.log(scale * rng.uniform(0.5, 2.0, (n, 4)))
        scales[:, 3] = np.log(rng.uniform(0.2, 1.0, n))
        sh = 0.1 * rng.standard_normal((n, nt + 1, K, 3))
        sh[:, 0, 0, :] = rng.uniform(-1, 1, (n, 3))
        return cls(means, scales, rng.standard_normal((n, 4)), rng.standard_normal((n, 4)),
                   rng.uniform(-2, 3, n), sh, rng.uniform(-np.pi, np.pi, (n, nt + 1)))


def quat_left(q: np.ndarray) -> np.ndarray:
    """[..., 4] (w, x, y, z) -> [..., 4, 4] matrix of v -> q * v (reference/project.py quat_left_matrix)."""
    a, b, c, d = np.moveaxis(q, -1, 0)
    return np.stack([np.stack([a, -b, -c, -d], -1), np.stack([b, a, -d, c], -1),
                     np.stack([c, d, a, -b], -1), np.stack([d, -c, b, a], -1)], -2)


def quat_right(q: np.ndarray) -> np.ndarray:
    """[..., 4] (w, x, y, z) -> [..., 4, 4] matrix of v -> v * q (reference/project.py quat_right_matrix)."""
    p, q1, r, s = np.moveaxis(q, -1, 0)
    return np.stack([np.stack([p, -q1, -r, -s], -1), np.stack([q1, p, s, -r], -1),
                     np.stack([r, -s, p, q1], -1), np.stack([s, r, -q1, p], -1)], -2)


def normalize_quat(q: np.ndarray) -> np.ndarray:
    """[N, 4] -> [N, 4] unit quaternions; the squared norm is clamped at 1e-24 (as
    reference/project.py normalize_quat) so that a zero quaternion gives 0, not NaN."""
    q = np.asarray(q, np.float64)
    return q / np.sqrt(np.maximum((q * q).sum(-1, keepdims=True), 1e-24))


def rotation_4d(g: Gaussians) -> np.ndarray:
    """[N, 4, 4] float64 rotations R = M_left(q_l) M_right(q_r) of the (unnormalised) quaternions.

    The numpy twin of reference/project.py rotation4d (torch): the same formulas in float64; the
    two may differ in the last bit (~1e-16) where the sums run in another order.
    """
    return quat_left(normalize_quat(g.quat_l)) @ quat_right(normalize_quat(g.quat_r))


def covariance_4d(g: Gaussians) -> np.ndarray:
    """[N, 4, 4] float64 Sigma = R S S^T R^T of every Gaussian (S = diag(exp(scales)))."""
    M = rotation_4d(g) * np.exp(g.scales.astype(np.float64))[:, None, :]  # R diag(S), [N, 4, 4]
    return M @ np.swapaxes(M, -1, -2)


def upload(rt, g: Gaussians) -> Dict[str, "object"]:
    """Copy the parameters to the device: {name: pyopencl.array.Array} in the same layout."""
    # an empty scene gives zero-size arrays whose .data is None: ops return early for N = 0
    return {name: cla.to_device(rt.queue, arr) for name, arr in g.as_dict().items()}


def download(params) -> Gaussians:
    return Gaussians(**{name: params[name].get() for name in PARAM_NAMES})
