"""Divergence guard: stop a run that has gone bad before it overwrites good checkpoints.

The per-step NaN guard (Trainer._check_finite) only sees the loss and the gradients.  Training can
go bad without either turning NaN (measured on a 64x48 synthetic scene, 60 steps):
  * lr_scales = 1e3: NaN scales and means, finite loss;
  * lr_position_init = 1e3 or lr_time = 1e3: means run to tens (Adam skipping culled Gaussians) or
    thousands of scene extents (or times of +-5000), nothing is rendered, the training PSNR sinks
    to ~9 dB;
  * lr_features = 1e3: colours blow up, the training PSNR drops from ~13 to below 0 dB;
  * densification can prune every Gaussian.
``DivergenceGuard.check`` tests for each of these at every log step and before every checkpoint
and raises TrainingDiverged, so the checkpoints on disk are the ones that passed.
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from ..errors import EndowaveError
from ..ops.util import any_nonfinite

# the training PSNR (EMA) falling this far below its best since the last opacity reset is a
# collapse: a healthy run's EMA dips by ~1-3 dB between frames, the runs above lose 10-30 dB
COLLAPSE_DB = 10.0
# a Gaussian is a runaway when its spatial distance from the initial point cloud's centre exceeds
# this many scene extents, or its time centre lies this far outside [0, 1]; in a healthy run the
# median is about 0.5 extent and the farthest Gaussian about 1.4 (pulling, demo).  With Adam
# skipping culled Gaussians (adam_skip_culled) a runaway stops where it leaves the view, some tens
# of extents out (lr_position_init = 1e3 on the tiny scene: median 32), not thousands
RUNAWAY_EXTENTS = 10.0
RUNAWAY_TIME = 100.0
# an opacity reset drops the PSNR on purpose and the EMA follows over ~20 steps; the collapse test
# pauses this many steps after one (opacities recover in ~100 steps at the default lr_opacity) and
# then measures against the recovered run only
RESET_GRACE_STEPS = 200


MAX_LOG_SCALE = 40.0   # |log std| beyond this (std > 2e17 or < 4e-18 units) is a runaway scale


class TrainingDiverged(EndowaveError):
    """Training produced non-finite or runaway values; the run stopped without saving them."""


class DivergenceGuard:
    def __init__(self, extent: float, center: np.ndarray):
        self.extent = float(extent)
        self.center = np.asarray(center, np.float64).reshape(3)
        self.best_psnr: Optional[float] = None
        self.quiet_until = -1

    def reset_reference(self, step: int) -> None:
        """After an opacity reset: forget the best PSNR and pause the collapse test a while."""
        self.best_psnr = None
        self.quiet_until = step + RESET_GRACE_STEPS

    def observe(self, step: int, psnr: Optional[float]) -> None:
        """Every step: raise TrainingDiverged when the training PSNR (its EMA) collapsed."""
        if psnr is None or not math.isfinite(psnr) or step <= self.quiet_until:
            return
        if self.best_psnr is not None and psnr < self.best_psnr - COLLAPSE_DB:
            raise TrainingDiverged(f"step {step}: training PSNR collapsed to {psnr:.2f} dB from "
                                   f"{self.best_psnr:.2f} dB (learning rates too high?)")
        self.best_psnr = psnr if self.best_psnr is None else max(self.best_psnr, psnr)

    def check(self, step: int, params, rt) -> None:
        """At log steps and before every save: raise TrainingDiverged when every Gaussian is gone or
        the parameters are non-finite or have run away.  ``params``: the device parameter arrays."""
        n = len(params["means"])
        if n == 0:
            raise TrainingDiverged(f"step {step}: every Gaussian was pruned (often a huge lr_opacity, "
                                   f"or prune_opacity too high)")
        # a log scale this large is an infinite Gaussian: its covariance overflows float32
        if any_nonfinite(rt, params.values()) or float(np.abs(params["scales"].get()).max(initial=0.0)) > MAX_LOG_SCALE:
            raise TrainingDiverged(f"step {step}: the parameters became NaN or infinite (learning rates "
                                   f"too high?)")
        means = params["means"].get().astype(np.float64)
        dist = np.linalg.norm(means[:, :3] - self.center, axis=1) / self.extent
        t_out = np.maximum(0.0, np.maximum(-means[:, 3], means[:, 3] - 1.0))
        if np.median(dist) > RUNAWAY_EXTENTS or np.median(t_out) > RUNAWAY_TIME:
            raise TrainingDiverged(f"step {step}: the Gaussians ran away (median distance "
                                   f"{np.median(dist):.3g} scene extents, median time offset "
                                   f"{np.median(t_out):.3g}): position or time learning rate too high?")
