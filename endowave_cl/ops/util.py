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

# The step gate's bits (cl/util.cl step_gate): why a step's update was left out on the device
GATE_NONFINITE = 1    # its gradients or loss sums hold a NaN or an Inf
GATE_ROWS = 2         # its live rows overflowed their buffer (ops/select.py)
GATE_PAIRS = 4        # its binning's pairs overflowed theirs (ops/binning.py)
GATE_SUPERVISED = 8   # its target supervises no pixel (a count only the device knew)
GATE_BITS = {"GATE_NONFINITE": GATE_NONFINITE, "GATE_ROWS": GATE_ROWS, "GATE_PAIRS": GATE_PAIRS,
             "GATE_SUPERVISED": GATE_SUPERVISED}


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


def average_into(rt, avg, x, w: float) -> None:
    """avg += w (x - avg), elementwise, for float32 device arrays of the same size (enqueued, not
    waited on): with w = 1 / k at the k-th snapshot, avg stays the mean of the snapshots."""
    if avg.size != x.size:
        raise ValueError(f"average_into: sizes differ ({avg.size} and {x.size})")
    if avg.size:
        rt.launch_1d(rt.kernel("util.cl", "average_into_f32"), avg.size, WORK_GROUP, avg.data, x.data,
                     np.float32(w), np.int32(avg.size))


def any_nonfinite(rt, arrays) -> bool:
    """True when any element of the given float32 device arrays is NaN or infinite (one read-back)."""
    return bool(nonfinite_flag(rt, arrays).get()[0])


def read_back(rt, arrays: Mapping[str, object]) -> Dict[str, np.ndarray]:
    """Host copies of several small device arrays with one blocking read: each is copied (on the
    device, in queue order) into one staging buffer, which is read once.  {name: numpy array of
    the same dtype and shape}; empty arrays come back empty."""
    return PendingRead(rt, arrays).result()


class PendingRead:
    """read_back without the wait: the arrays' copies into one staging buffer and its copy to the
    host are enqueued at once (in queue order, so they hold the values the work enqueued before
    gave them), and result() waits for that copy only, typically long done by then."""

    def __init__(self, rt, arrays: Mapping[str, object]):
        self._layout, total = [], 0
        for name, a in arrays.items():
            self._layout.append((name, a.dtype, tuple(a.shape), int(a.nbytes), total))
            total += -(-int(a.nbytes) // READBACK_ALIGN) * READBACK_ALIGN
        self._host = np.empty(total, np.uint8)
        self._event = None
        if total == 0:
            return
        staging = cla.empty(rt.queue, (total,), np.uint8)
        for name, a in arrays.items():
            if a.nbytes and not a.flags.c_contiguous:
                raise ValueError(f"read_back: {name!r} is not C-contiguous")
        for (name, _, _, nbytes, off), a in zip(self._layout, arrays.values()):
            if nbytes:
                cl.enqueue_copy(rt.queue, staging.data, a.base_data, byte_count=nbytes, dst_offset=off,
                                src_offset=int(a.offset))
        self._event = cl.enqueue_copy(rt.queue, self._host, staging.data, is_blocking=False)

    @property
    def done(self) -> bool:
        """True when result() would not wait."""
        return self._event is None or self._event.command_execution_status == cl.command_execution_status.COMPLETE

    def result(self) -> Dict[str, np.ndarray]:
        """{name: numpy array of the same dtype and shape} (waits for the copy where it is pending)."""
        if self._event is not None:
            self._event.wait()
            self._event = None
        return {name: self._host[off:off + nbytes].view(dtype).reshape(shape).copy()
                for name, dtype, shape, nbytes, off in self._layout}


def step_gate(rt, skip, nonfinite_grads, nonfinite_loss, rows=None, pairs=None, supervised=None) -> None:
    """Enqueue skip [1] int32 |= the GATE_* bits of a step (cl/util.cl step_gate; reference:
    reference/util.py step_gate_ref): nonfinite_grads, nonfinite_loss: int32 [1] flags
    (nonfinite_flag of the gradients and of the loss sums); rows, pairs:
    ops.binning.PairCount (count and capacity) of the step's live rows and binning, or None;
    supervised: an int32 [1] device count of supervised pixels, or None where the host knew it."""
    def count_arg(pc):
        at = None if pc is None else pc.device_at()
        if at is None:            # known on the host when the buffer was sized: nothing to test
            return [rt.dummy_buffer(), np.int32(0), np.int32(-1)]
        return [at[0], np.int32(at[1]), np.int32(pc.capacity)]
    k = rt.kernel("util.cl", "step_gate", [f"-D{name}={bit}" for name, bit in GATE_BITS.items()])
    rt.launch(k, (1,), (1,), nonfinite_grads.data, nonfinite_loss.data, *count_arg(rows), *count_arg(pairs), rt.buf(supervised),
              np.int32(supervised is not None), skip.data)
