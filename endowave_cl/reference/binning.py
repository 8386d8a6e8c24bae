"""numpy references of tile binning and tile ranges (docs/ARCHITECTURE.md); the sort's are in
reference/sort.py (sort_pairs_ref is re-exported here)."""
from __future__ import annotations

import numpy as np

from ..layout import TILE, tile_grid  # noqa: F401  (re-exported: tests and tools take them from here)
from .sort import sort_pairs_ref  # noqa: F401  (re-exported: probe.py, tests and tools take it from here)


def bin_gaussians_ref(rect: np.ndarray, depth: np.ndarray, radius: np.ndarray, tiles_x: int):
    """Unsorted (keys, values) in the kernel's order: Gaussian by Gaussian, tiles row-major.

    rect [N, 4] int (x0, y0, x1, y1) exclusive; depth [N] float32; radius [N] int.
    """
    keys, vals = [], []
    dbits = np.ascontiguousarray(depth, np.float32).view(np.uint32).astype(np.uint64)
    for i in range(len(depth)):
        if radius[i] <= 0:
            continue
        x0, y0, x1, y1 = (int(v) for v in rect[i])
        for ty in range(y0, y1):
            for tx in range(x0, x1):
                keys.append((np.uint64(ty * tiles_x + tx) << np.uint64(32)) | dbits[i])
                vals.append(i)
    return np.array(keys, np.uint64), np.array(vals, np.int32)


def bin_offsets_ref(rect: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """[N + 1] int32: where each Gaussian's entries start in the unsorted list of
    bin_gaussians_ref (its rect's area when radius > 0, else 0, scanned), then the total."""
    rect = np.asarray(rect, np.int64).reshape(-1, 4)
    area = np.maximum(rect[:, 2] - rect[:, 0], 0) * np.maximum(rect[:, 3] - rect[:, 1], 0)
    counts = np.where(np.asarray(radius) > 0, area, 0)
    return np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)


def tile_ranges_ref(sorted_keys: np.ndarray, n_tiles: int) -> np.ndarray:
    """[n_tiles, 2] int32 (start, end) of each tile in the sorted list; (0, 0) when empty."""
    ranges = np.zeros((n_tiles, 2), np.int32)
    tiles = (sorted_keys >> np.uint64(32)).astype(np.int64)
    if len(tiles):
        ids = np.arange(n_tiles)
        start = np.searchsorted(tiles, ids, "left")
        end = np.searchsorted(tiles, ids, "right")
        has = end > start
        ranges[has, 0] = start[has]
        ranges[has, 1] = end[has]
    return ranges
