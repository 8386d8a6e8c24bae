"""Exclusive prefix sum of int32 on the device (cl/scan.cl).

Work-group scans of blocks of ``SCAN_WG * SCAN_ITEMS`` values, then (recursively) a scan
of the block totals, then a pass adding each block's offset.  Sums wrap at 2^31.
"""
from __future__ import annotations

from typing import Tuple

import numpy as np
import pyopencl.array as cla

SCAN_WG = 256     # work-items per group (power of two)
SCAN_ITEMS = 8    # consecutive values per work-item
SCAN_BLOCK = SCAN_WG * SCAN_ITEMS


def _options():
    return [f"-DSCAN_WG={SCAN_WG}", f"-DSCAN_ITEMS={SCAN_ITEMS}"]


def exclusive_scan_into(rt, x: cla.Array, n_in: int, out: cla.Array, n_out: int) -> None:
    """Enqueue out[k] = sum_{j<k} x[j] for k < n_out (x[j] read as 0 for j >= n_in).

    No host synchronisation; ``n_out = n_in + 1`` puts the grand total in ``out[n_in]``.
    x, out: int32 device arrays with at least n_in / n_out elements.
    """
    if n_out <= 0:
        return
    n_groups = (n_out + SCAN_BLOCK - 1) // SCAN_BLOCK
    sums = rt.empty(n_groups, np.int32)  # [n_groups]
    k = rt.kernel("scan.cl", "scan_blocks", _options())
    rt.launch(k, (n_groups * SCAN_WG,), (SCAN_WG,), x.data if n_in > 0 else sums.data,
              np.int32(n_in), out.data, np.int32(n_out), sums.data)
    if n_groups > 1:
        offs = rt.empty(n_groups, np.int32)  # [n_groups]
        exclusive_scan_into(rt, sums, n_groups, offs, n_groups)
        add = rt.kernel("scan.cl", "scan_add_offsets", _options())
        wg = min(SCAN_WG, rt.max_work_group_size)
        rt.launch_1d(add, n_out, wg, out.data, np.int32(n_out), offs.data)


def exclusive_scan_with_total(rt, x: cla.Array) -> cla.Array:
    """[n + 1] int32: the exclusive scan of x [n] followed by the total (no host sync)."""
    n = int(x.size)
    out = rt.empty(n + 1, np.int32)
    exclusive_scan_into(rt, x, n, out, n + 1)
    return out


def exclusive_scan(rt, x: cla.Array) -> Tuple[cla.Array, int]:
    """(offsets [n] int32, total) with offsets[k] = sum_{j<k} x[j]; x is int32 [n]."""
    if x.dtype != np.int32:
        raise TypeError(f"exclusive_scan takes int32, got {x.dtype}")
    n = int(x.size)
    full = exclusive_scan_with_total(rt, x)  # [n + 1]
    total = int(full[n:n + 1].get()[0])
    return full[:n], total
