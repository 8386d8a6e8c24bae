"""The parameters averaged over the last steps of a run (stochastic weight averaging).

Each step fits one image (a training frame or an in-between time), so the parameters at the last
step lean towards the last few images and carry the steps' noise.  The uniform mean of snapshots
taken over the run's last `average_last` fraction of steps keeps what the late steps agree on.
The mean is kept on the device (cl/util.cl average_into_f32), a snapshot every AVERAGE_EVERY steps,
and only once the rows are fixed (after densify_until: density control replaces rows, and the
trainer drops the mean whenever it does).  The optimisation itself is unchanged: the mean is what
the run saves at its end, beside the last step's figures in train_log.json.  The mean is not in
the checkpoints: a run resumed inside the window starts it again at the step it resumes from.
"""
from __future__ import annotations

import math
from typing import Dict

import pyopencl as cl

from ..ops.util import average_into

AVERAGE_EVERY = 10   # steps between snapshots: neighbouring steps' parameters differ little


def average_start(cfg) -> int:
    """The first step whose parameters enter the mean (cfg.iterations + 1: no averaging)."""
    if not cfg.average_last > 0:
        return cfg.iterations + 1
    return max(int(cfg.densify_until) + 1, int(math.ceil(cfg.iterations * (1.0 - cfg.average_last) - 1e-9)))


class ParameterAverage:
    """The running mean of the parameter arrays {name: [N, ...] float32} from step `first` on."""

    def __init__(self, rt, params: Dict[str, object], first: int):
        self.rt, self.first, self.count = rt, int(first), 1
        self.mean = {name: arr.copy(queue=rt.queue) for name, arr in params.items()}

    def due(self, step: int) -> bool:
        return step > self.first and (step - self.first) % AVERAGE_EVERY == 0

    def add(self, params: Dict[str, object]) -> None:
        """One more snapshot, enqueued behind the step that produced it."""
        self.count += 1
        for name, arr in params.items():
            average_into(self.rt, self.mean[name], arr, 1.0 / self.count)

    def copy_to(self, params: Dict[str, object]) -> None:
        """Write the mean into the parameter arrays in place (the optimiser keeps its references)."""
        for name, arr in params.items():
            if arr.size:
                cl.enqueue_copy(self.rt.queue, arr.data, self.mean[name].data, byte_count=arr.nbytes)
