"""A training schedule planned to end within a wall-clock budget (``--minutes``).

The step count that fits depends on the device, the image size and how many Gaussians density
control grows, so it is measured, not guessed: after a few warm-up steps (kernel builds) the
trainer times its steps and re-plans at every log interval.  A plan keeps the configured
schedule's *shape*: densification window, opacity reset and position-lr decay stay at the same
fractions of the run.  A hard deadline stops the loop in any case, leaving time for the final
checkpoint and evaluation.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Dict, Optional

from .config import SCALED_FIELDS   # schedule fields that are step counts: they scale with the plan
WARMUP_STEPS = 5          # first steps build kernels: not timed
MIN_TIMED_STEPS = 20      # steps timed before the first plan
RATE_WINDOW = 100         # steps over which the current rate is measured
# While density control still adds Gaussians, later steps cost more than the recent ones:
# plan this fraction of what the recent rate allows (after densification: all of it).
GROWTH_MARGIN = 0.8


@dataclass
class BudgetPlan:
    """A time-budgeted schedule; ``replan`` gives the trainer's config with the planned schedule."""
    seconds: float                 # whole budget of the training loop
    reserve: float                 # kept for the final checkpoint and evaluation
    base: Dict[str, int]           # the configured iterations and SCALED_FIELDS
    t_start: float = 0.0
    planned: Optional[int] = None  # current planned step count

    @classmethod
    def start(cls, cfg, minutes: float, reserve: float, t_start: Optional[float] = None) -> "BudgetPlan":
        base = {"iterations": int(cfg.iterations), **{f: int(getattr(cfg, f)) for f in SCALED_FIELDS}}
        if not base["lr_position_steps"]:
            base["lr_position_steps"] = base["iterations"]
        return cls(float(minutes) * 60.0, float(reserve), base,
                   time.perf_counter() if t_start is None else float(t_start))

    @property
    def deadline(self) -> float:
        return self.t_start + self.seconds - self.reserve

    def out_of_time(self) -> bool:
        return time.perf_counter() >= self.deadline

    def replan(self, cfg, step: int, seconds_per_step: float):
        """cfg (a TrainConfig) with iterations and the scaled fields planned for the time left at
        ``seconds_per_step``; ``planned`` holds the new iterations."""
        left = max(0.0, self.deadline - time.perf_counter())
        margin = GROWTH_MARGIN if step < cfg.densify_until else 1.0
        total = max(step + 1, step + int(margin * left / max(seconds_per_step, 1e-6)))
        r = total / self.base["iterations"]
        scaled = {f: max(1, int(round(self.base[f] * r))) if self.base[f] > 0 else 0   # a key at 0 (off) stays 0
                  for f in SCALED_FIELDS}
        self.planned = total
        return cfg.replace(iterations=total, **scaled)
