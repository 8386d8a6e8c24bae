"""select host op: the Gaussians alive at time t, gathered into compact parameter arrays.

A 4D Gaussian lives for a part of the sequence: at any one time most of a trained model's rows are
culled by project4d's temporal test (marginal weight below MARGINAL_CULL) and every stage after it
only carries their zeros.  ``select_live`` finds a superset of the rows that pass that test
(cl/select.cl live_flags: a slack below the threshold absorbs rounding), their indices in
ascending order (a scan), and copies their parameters into arrays of that many rows.  Rendering
and its adjoint on those arrays give, for every selected row, the values the full arrays give
(each stage computes per Gaussian; the sort is stable and the rows keep their order), and the
rows left out would have been culled: the training step updates the full parameters through
``LiveRows.rows`` (ops.adam.DeviceAdam.step(rows=...), ops.rasterize.accumulate_densify_stats).

Kernels: cl/select.cl.  Reference: endowave_cl/reference/select.py.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, Optional

import numpy as np

from .. import env
from ..gaussians import MARGINAL_CULL, PARAM_NAMES
from ..layout import ALPHA_MIN
from .project import launch_lanes
from .scan import exclusive_scan_with_total
from .util import f32_literal

WORK_GROUP = 128
SELECT_MAX_SHARE = 0.5   # render(select=True) gathers the rows when at most this share of them is alive:
                         # above it the gather and Adam on rows cost more than the culled rows do
ENV_NO_SELECT = "ENDOWAVE_NO_SELECT"   # 1: training renders every Gaussian (benchmarks compare the two)
LIVE_SLACK = 0.99    # LIVE_SLACK in cl/select.cl: rows down to 0.99 x MARGINAL_CULL are selected


def select_enabled() -> bool:
    """False when $ENDOWAVE_NO_SELECT asks training to render every Gaussian (the same results)."""
    return not env.flag(ENV_NO_SELECT)


def _options():
    """select.cl's build options (it includes project4d_common.h, which reads these)."""
    return [f"-DMARGINAL_CULL={f32_literal(MARGINAL_CULL)}", f"-DALPHA_MIN={f32_literal(ALPHA_MIN)}"]


def dt2_per_stt_max() -> float:
    """The largest (t - mu_t)^2 / Sigma_tt that live_flags keeps: -2 ln(MARGINAL_CULL LIVE_SLACK)."""
    return -2.0 * math.log(MARGINAL_CULL * LIVE_SLACK)


@dataclass
class LiveRows:
    rows: object                  # cla int32 [L]: indices of the selected Gaussians, ascending
    params: Dict[str, object]     # {name: cla [L, ...]}: their parameters (PARAM_NAMES)
    n_full: int                   # N, the rows of the full parameter arrays

    def __len__(self) -> int:
        return int(self.rows.shape[0])


def live_flags(rt, params: Dict[str, object], t: float):
    """cla int32 [N]: 1 for the Gaussians that may be alive at t (cl/select.cl live_flags)."""
    n = int(params["means"].shape[0])
    flags = rt.empty((n,), np.int32)
    if n:
        launch_lanes(rt, "select.cl", "live_flags", _options(), n,
                     np.int32(n), params["means"].data, params["scales"].data, params["quat_l"].data,
                     params["quat_r"].data, np.float32(t), np.float32(dt2_per_stt_max()), flags.data)
    return flags


def gather_params(rt, params: Dict[str, object], rows, n_rows: int) -> Dict[str, object]:
    """{name: cla [n_rows, ...] = params[name][rows]} for PARAM_NAMES (rows: cla int32 [n_rows])."""
    out = {name: rt.empty((n_rows,) + tuple(int(s) for s in params[name].shape[1:]), np.float32)
           for name in PARAM_NAMES}
    if n_rows:
        widths = {name: int(np.prod(params[name].shape[1:], dtype=np.int64)) for name in ("sh", "phase")}
        k = rt.kernel("select.cl", "gather_params", _options() + [f"-DSH_W={widths['sh']}", f"-DPHASE_W={widths['phase']}"])
        rt.launch_1d(k, n_rows, WORK_GROUP, np.int32(n_rows), rows.data,
                     *[params[name].data for name in PARAM_NAMES], *[out[name].data for name in PARAM_NAMES])
    return out


def select_live(rt, params: Dict[str, object], t: float, max_share: float = 1.0) -> Optional[LiveRows]:
    """The Gaussians that may be alive at t and their parameters (one blocking read: the count);
    None when more than max_share of the rows are selected (nothing is gathered then)."""
    n = int(params["means"].shape[0])
    flags = live_flags(rt, params, t)
    if n == 0:
        count = 0
        rows = rt.empty((0,), np.int32)
    else:
        offsets = exclusive_scan_with_total(rt, flags)   # [N + 1]
        count = int(offsets[n:n + 1].get()[0])
        if count > max_share * n:
            return None
        rows = rt.empty((count,), np.int32)
        if count:
            rt.launch_1d(rt.kernel("select.cl", "live_rows", _options()), n, WORK_GROUP, np.int32(n), flags.data,
                         offsets.data, rows.data)
    return LiveRows(rows, gather_params(rt, params, rows, count), n)
