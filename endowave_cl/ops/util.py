"""Small device utilities on top of cl/util.cl."""
from __future__ import annotations

import numpy as np

WORK_GROUP = 128


def any_nonfinite(rt, arrays) -> bool:
    """True when any element of the given float32 device arrays is NaN or infinite (one read-back)."""
    import pyopencl.array as cla
    flag = cla.zeros(rt.queue, (1,), np.int32)
    k = rt.kernel("util.cl", "any_nonfinite_f32")
    for a in arrays:
        if a.size == 0:
            continue
        rt.launch_1d(k, a.size, WORK_GROUP, a.data, np.int32(a.size), flag.data)
    return bool(flag.get()[0])
