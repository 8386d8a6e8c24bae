"""numpy reference of the exclusive scan (cl/scan.cl, ops/scan.py); the sort's references are in
reference/sort.py."""
from __future__ import annotations

from typing import Tuple

import numpy as np


def exclusive_scan_ref(x: np.ndarray) -> Tuple[np.ndarray, int]:
    """(offsets [n] int32, total) with offsets[k] = sum_{j<k} x[j] (int32 wrap-around)."""
    x = np.asarray(x, np.int32)
    c = np.cumsum(x, dtype=np.int64)
    offsets = np.zeros(len(x), np.int64)
    offsets[1:] = c[:-1]
    total = int(c[-1]) if len(x) else 0
    return offsets.astype(np.int32), total
