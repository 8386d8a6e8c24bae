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

``select_live(check=False)`` reads nothing back: the rows buffer holds C rows, C sized from the live
shares of earlier selections (LiveCapacity: HEADROOM times the latest share of the rows, grown at
once), the rows past the selected count L padded with -1 and their gathered parameters a Gaussian
that is culled at every time (so every later stage skips them as it skips any culled row).  L is
copied to the host without blocking (LiveRows.count, an ops.binning.PairCount) and checked where the
caller next waits on the device: an overflow (L > C: rows past C left out) is never used, the
training step renders again with check=True (Trainer._step), which reads L and sizes C to it.

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
from .binning import PairCount
from .project import launch_lanes
from .scan import exclusive_scan_with_total
from .util import f32_literal

WORK_GROUP = 128
SELECT_MAX_SHARE = 0.5   # render(select=True) gathers the rows when at most this share of them is alive:
                         # above it the gather and Adam on rows cost more than the culled rows do
ENV_NO_SELECT = "ENDOWAVE_NO_SELECT"   # 1: training renders every Gaussian (benchmarks compare the two)
LIVE_SLACK = 0.99    # LIVE_SLACK in cl/select.cl: rows down to 0.99 x MARGINAL_CULL are selected
HEADROOM = 1.25      # the rows buffer of select_live(check=False): this many times the latest live share
MIN_ROWS = 256       # and at least this many rows (never more than N)
DEAD_T = 1.0e4       # a padding row's time: 10^4 sequences away, culled at every time in [0, 1]
DEAD_OPACITY = -30.0 # and its opacity logit (sigmoid ~ 1e-13), should anything ever read it


def select_enabled() -> bool:
    """False when $ENDOWAVE_NO_SELECT asks training to render every Gaussian (the same results)."""
    return not env.flag(ENV_NO_SELECT)


def _options():
    """select.cl's build options (it includes project4d_common.h, which reads these)."""
    return [f"-DMARGINAL_CULL={f32_literal(MARGINAL_CULL)}", f"-DALPHA_MIN={f32_literal(ALPHA_MIN)}",
            f"-DDEAD_T={f32_literal(DEAD_T)}", f"-DDEAD_OPACITY={f32_literal(DEAD_OPACITY)}"]


class LiveCapacity:
    """The rows buffer's length C that select_live(check=False) gives N Gaussians: HEADROOM times
    the latest live share L / N seen (at least MIN_ROWS, at most N), grown as soon as a share needs
    more, shrunk only where it needs less than half (shares that vary with t keep one size).  A
    share, not a count, so that densification and pruning carry it over.  latest: the latest share
    seen (SELECT_MAX_SHARE is tested on it); pending: the latest count not yet seen (a PairCount
    whose copy is enqueued), taken in by settle()."""

    def __init__(self):
        self.share: Optional[float] = None
        self.latest: Optional[float] = None
        self.pending: Optional[PairCount] = None

    def observe(self, count: int, n: int) -> None:
        self.latest = int(count) / max(int(n), 1)
        need = self.latest * HEADROOM
        if self.share is None or need > self.share or 2 * need < self.share:
            self.share = need

    def settle(self) -> None:
        """Take in the pending count where its copy has completed (where a step's read-back ran
        since); one still in flight is left to its LiveRows (renders with no wait between them)."""
        if self.pending is not None and not self.pending.pending:
            pending, self.pending = self.pending, None
            pending.value()

    def capacity(self, n: int) -> int:
        return min(int(n), max(MIN_ROWS, math.ceil(self.share * int(n))))


class _Observer:
    """PairCount's policy for a live count: LiveCapacity.observe with the N it was counted among."""

    def __init__(self, policy: LiveCapacity, n: int):
        self.policy, self.n = policy, int(n)

    def observe(self, count: int) -> None:
        self.policy.observe(count, self.n)


def live_capacity(rt) -> LiveCapacity:
    """The runtime's LiveCapacity (every selection on the runtime's device shares it)."""
    return rt.cached(("select.live_capacity",), LiveCapacity)


def dt2_per_stt_max() -> float:
    """The largest (t - mu_t)^2 / Sigma_tt that live_flags keeps: -2 ln(MARGINAL_CULL LIVE_SLACK)."""
    return -2.0 * math.log(MARGINAL_CULL * LIVE_SLACK)


@dataclass
class LiveRows:
    rows: object                  # cla int32 [C]: indices of the selected Gaussians, ascending, then -1
    params: Dict[str, object]     # {name: cla [C, ...]}: their parameters (PARAM_NAMES; padding: culled)
    n_full: int                   # N, the rows of the full parameter arrays
    count: PairCount              # L, the selected count (read without blocking), and C

    def __len__(self) -> int:
        return int(self.rows.shape[0])

    @property
    def overflowed(self) -> bool:
        """L > C: rows past C were left out and the render is not to be used (waits for L's copy)."""
        return self.count.overflowed


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
    """{name: cla [n_rows, ...] = params[name][rows]} for PARAM_NAMES (rows: cla int32 [n_rows]; a
    row -1 gives the culled padding Gaussian)."""
    out = {name: rt.empty((n_rows,) + tuple(int(s) for s in params[name].shape[1:]), np.float32)
           for name in PARAM_NAMES}
    if n_rows:
        widths = {name: int(np.prod(params[name].shape[1:], dtype=np.int64)) for name in ("sh", "phase")}
        k = rt.kernel("select.cl", "gather_params", _options() + [f"-DSH_W={widths['sh']}", f"-DPHASE_W={widths['phase']}"])
        rt.launch_1d(k, n_rows, WORK_GROUP, np.int32(n_rows), rows.data,
                     *[params[name].data for name in PARAM_NAMES], *[out[name].data for name in PARAM_NAMES])
    return out


def _rows(rt, flags, offsets, n: int, cap: int):
    """cla int32 [cap]: the first min(L, cap) selected rows, then -1 (cl/select.cl live_rows)."""
    rows = rt.empty((cap,), np.int32)
    if cap:
        rt.launch_1d(rt.kernel("select.cl", "live_rows", _options()), n, WORK_GROUP, np.int32(n), flags.data,
                     offsets.data, np.int32(cap), rows.data)
    return rows


def select_live(rt, params: Dict[str, object], t: float, max_share: float = 1.0,
                check: bool = True) -> Optional[LiveRows]:
    """The Gaussians that may be alive at t and their parameters; None when more than max_share of
    the rows are selected (nothing is gathered then).
    check: read the count L (one blocking read) and gather exactly L rows.  check=False reads
    nothing where the runtime's LiveCapacity has seen a count: C rows from it, padded (the module's
    docstring), max_share tested on the latest share seen, and L checked by the caller
    (LiveRows.overflowed after its own next wait on the device); the first selection reads L."""
    n = int(params["means"].shape[0])
    if n == 0:
        rows = rt.empty((0,), np.int32)
        return LiveRows(rows, gather_params(rt, params, rows, 0), 0, PairCount(0, 0))
    flags = live_flags(rt, params, t)
    offsets = exclusive_scan_with_total(rt, flags)   # [N + 1], offsets[N] = L
    policy = live_capacity(rt)
    policy.settle()
    if check or policy.share is None:
        count = int(offsets[n:n + 1].get()[0])
        policy.observe(count, n)
        if count > max_share * n:
            return None
        rows = _rows(rt, flags, offsets, n, count)
        return LiveRows(rows, gather_params(rt, params, rows, count), n, PairCount(count, count))
    cap = policy.capacity(n)
    pending = PairCount.enqueue_read(rt, offsets, n, cap, _Observer(policy, n))
    policy.pending = pending
    if policy.latest > max_share:
        return None
    rows = _rows(rt, flags, offsets, n, cap)
    return LiveRows(rows, gather_params(rt, params, rows, cap), n, pending)
