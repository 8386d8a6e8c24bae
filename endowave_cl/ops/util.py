"""Small device utilities on top of cl/util.cl, and the one blocking read-back of a step."""
from __future__ import annotations

from typing import Dict, Mapping

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

WORK_GROUP = 128
NONFINITE_RUN = 64    # elements per work-item of any_nonfinite_f32 (-DNF_RUN of cl/util.cl)
NONFINITE_ARRAYS = 8  # arrays per launch of any_nonfinite_f32 (its x0 .. x7)
READBACK_ALIGN = 16   # bytes: each array's region in the read-back buffer starts at a multiple of this


def f32_literal(x: float) -> str:
    """An OpenCL float literal that rounds to the same float32 as numpy does (for -D build options)."""
    return "%.9ef" % float(np.float32(x))


def nonfinite_flag(rt, arrays, flag=None):
    """Enqueue the NaN / Inf check of the given float32 device arrays, without reading it:
    returns flag (cla int32 [1], zeroed here when not given), 1 when any element is not finite.

    A factored SH gradient (ops.project.ShGradFactors) is checked through its factors: its values
    (gcol_c Y_k) cos_f are non-finite exactly when a factor is, since every factor enters some
    product (a NaN or Inf factor makes it NaN or Inf, 0 x Inf included) and |Y_k| <= 1, |cos_f| <= 1,
    so finite factors cannot overflow."""
    if flag is None:
        flag = cla.zeros(rt.queue, (1,), np.int32)
    k = rt.kernel("util.cl", "any_nonfinite_f32", [f"-DNF_RUN={NONFINITE_RUN}"])
    arrays = [a for a in (getattr(a, "factors", a) for a in arrays) if a.size]   # ShGradFactors: its factors
    for i in range(0, len(arrays), NONFINITE_ARRAYS):
        part = arrays[i:i + NONFINITE_ARRAYS]
        runs = max(-(-int(a.size) // NONFINITE_RUN) for a in part)
        args = []
        for j in range(NONFINITE_ARRAYS):   # unused slots: no elements (any buffer)
            a = part[j] if j < len(part) else None
            args += [part[0].data if a is None else a.data, np.int32(0 if a is None else a.size)]
        rt.launch(k, (-(-runs // WORK_GROUP) * WORK_GROUP, len(part)), (WORK_GROUP, 1), *args, flag.data)
    return flag


def add_inplace(rt, out, x) -> None:
    """out += x, elementwise, for float32 device arrays of the same size (enqueued, not waited on)."""
    if out.size != x.size:
        raise ValueError(f"add_inplace: sizes differ ({out.size} and {x.size})")
    if out.size:
        rt.launch_1d(rt.kernel("util.cl", "add_inplace_f32"), out.size, WORK_GROUP, out.data, x.data,
                     np.int32(out.size))


def any_nonfinite(rt, arrays) -> bool:
    """True when any element of the given float32 device arrays is NaN or infinite (one read-back)."""
    return bool(nonfinite_flag(rt, arrays).get()[0])


def read_back(rt, arrays: Mapping[str, object]) -> Dict[str, np.ndarray]:
    """Host copies of several small device arrays with one blocking read: each is copied (on the
    device, in queue order) into one staging buffer, which is read once.  {name: numpy array of
    the same dtype and shape}; empty arrays come back empty."""
    layout, total = [], 0
    for name, a in arrays.items():
        layout.append((name, a, total))
        total += -(-int(a.nbytes) // READBACK_ALIGN) * READBACK_ALIGN
    out: Dict[str, np.ndarray] = {}
    if total == 0:
        return {name: np.empty(a.shape, a.dtype) for name, a in arrays.items()}
    staging = cla.empty(rt.queue, (total,), np.uint8)
    for name, a, off in layout:
        if a.nbytes:
            if not a.flags.c_contiguous:
                raise ValueError(f"read_back: {name!r} is not C-contiguous")
            cl.enqueue_copy(rt.queue, staging.data, a.base_data, byte_count=int(a.nbytes), dst_offset=off,
                            src_offset=int(a.offset))
    host = staging.get()   # the blocking read
    for name, a, off in layout:
        out[name] = host[off:off + int(a.nbytes)].view(a.dtype).reshape(a.shape).copy()
    return out
