"""numpy reference of ops/select.py (cl/select.cl): which Gaussians may be alive at t, and their rows.

Float64 throughout: live_flags_ref is the exact test the kernel approximates in float32, so tests
compare away from the threshold and check the kernel's set against project4d's visible rows."""
from __future__ import annotations

from typing import Dict, Tuple

import numpy as np

from ..gaussians import MARGINAL_CULL, PARAM_NAMES, Gaussians, covariance_4d
from .project import SIGMA_TT_MIN


def marginal_ref(g: Gaussians, t: float) -> Tuple[np.ndarray, np.ndarray]:
    """(Sigma_tt [N], marginal weight m [N] at t), float64."""
    stt = covariance_4d(g)[:, 3, 3]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        m = np.exp(-0.5 * (t - g.means[:, 3].astype(np.float64)) ** 2 / stt)
    return stt, m


def live_flags_ref(g: Gaussians, t: float, slack: float) -> np.ndarray:
    """int32 [N]: 1 where m >= MARGINAL_CULL * slack and Sigma_tt > SIGMA_TT_MIN / 2 (NaN: 0)."""
    stt, m = marginal_ref(g, t)
    with np.errstate(invalid="ignore"):
        return ((stt > 0.5 * SIGMA_TT_MIN) & (m >= MARGINAL_CULL * slack)).astype(np.int32)


def select_live_ref(g: Gaussians, flags: np.ndarray) -> Tuple[np.ndarray, Dict[str, np.ndarray]]:
    """(rows [L] int32 ascending, {name: parameters of those rows}) of the flagged Gaussians."""
    rows = np.flatnonzero(flags).astype(np.int32)
    return rows, {name: getattr(g, name)[rows] for name in PARAM_NAMES}
