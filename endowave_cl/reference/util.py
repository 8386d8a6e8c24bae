"""numpy reference of the step gate (cl/util.cl step_gate, ops/util.py step_gate)."""
from __future__ import annotations

from typing import Optional

import numpy as np

from ..ops.util import GATE_NONFINITE, GATE_PAIRS, GATE_ROWS, GATE_SUPERVISED


def step_gate_ref(skip: int, nonfinite_grads: int, nonfinite_loss: int, rows_count: Optional[int] = None,
                  rows_cap: int = -1, pairs_count: Optional[int] = None, pairs_cap: int = -1,
                  supervised: Optional[int] = None) -> int:
    """The gate's new value: skip with the bit of every reason the step must not be applied set
    (a count None, or a capacity < 0, is not tested; supervised None: known on the host)."""
    s = int(skip)
    if nonfinite_grads or nonfinite_loss:
        s |= GATE_NONFINITE
    if rows_count is not None and rows_cap >= 0 and rows_count > rows_cap:
        s |= GATE_ROWS
    if pairs_count is not None and pairs_cap >= 0 and pairs_count > pairs_cap:
        s |= GATE_PAIRS
    if supervised is not None and supervised == 0:
        s |= GATE_SUPERVISED
    return s


def average_into_ref(avg: np.ndarray, x: np.ndarray, w: float) -> np.ndarray:
    """avg + w (x - avg) in float32 (cl/util.cl average_into_f32, ops/util.py average_into)."""
    avg = np.asarray(avg, np.float32)
    return avg + np.float32(w) * (np.asarray(x, np.float32) - avg)
