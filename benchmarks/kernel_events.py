"""Kernel time by OpenCL event profiling, for the benchmark tools (perf_table, bench_train_step).

    events = profile_launches(rt)   # before any buffer or kernel of rt is used
    ...                             # work launched through rt.launch / rt.launch_1d
    rt.queue.finish()
    per_kernel = kernel_ms(events)  # {kernel name: summed ms}; events.clear() for the next round

The runtime's queue is replaced by a profiling one and its two launch methods by wrappers that keep
(kernel name, event).  Only launches through the Runtime are seen: pyopencl's own element-wise
kernels (fill, zeros) and buffer copies are not, so the sum is a lower bound on the device's busy
time.  Set it up before the first pool allocation: the memory pool is bound to the queue it was
made with.
"""
from __future__ import annotations

from collections import defaultdict
from typing import Dict, List, Tuple


def profile_launches(rt) -> List[Tuple[str, object]]:
    """Make rt's queue a profiling queue and record every Runtime launch; returns the (growing) list
    of (kernel name, event)."""
    import pyopencl as cl
    rt.queue = cl.CommandQueue(rt.ctx, properties=cl.command_queue_properties.PROFILING_ENABLE)
    events: List[Tuple[str, object]] = []
    plain_launch, plain_launch_1d = rt.launch, rt.launch_1d

    def launch(kernel, *a):
        ev = plain_launch(kernel, *a)
        events.append((kernel.function_name, ev))
        return ev

    def launch_1d(kernel, *a):
        ev = plain_launch_1d(kernel, *a)
        events.append((kernel.function_name, ev))
        return ev
    rt.launch, rt.launch_1d = launch, launch_1d
    return events


def kernel_ms(events) -> Dict[str, float]:
    """{kernel name: summed event time in ms} of finished events."""
    tot: Dict[str, float] = defaultdict(float)
    for name, ev in events:
        tot[name] += (ev.profile.end - ev.profile.start) * 1e-6
    return dict(tot)
