"""Per-step weights of the training steps (TrainConfig frame_balance).

The figure a reconstruction is judged by is the mean PSNR over frames, the mean of
-10 log10(MSE_f).  Its gradient weighs each frame's error gradient by 1 / MSE_f: a frame the model
already fits well (a nearly still one, 43 dB) counts as much as a badly fitted one though its
errors are a fraction of the size.  A plain sum of per-frame losses weighs frames by the size of
their errors instead, so the well-fitted frames get the least of the optimiser's attention.

FrameBalance gives a step whose L1 loss is L the weight (G / L)^power, G the running geometric mean
of the losses of the step's kind ("plain" or "between", so that the in-between steps keep their
share of the gradient), clipped to [1 / MAX_WEIGHT, MAX_WEIGHT]. With power 1 the weighted
gradient is G times that of log L: the steps follow the mean of the frames' log losses. 0 weighs
every step alike.  The trainer multiplies the step's gradient by the weight inside Adam
(ops/adam.py grad_scale), after the densification statistics are taken, so that density control
sees the unweighted gradients.

G is not kept in checkpoints: a resumed run starts it again from its first step of each kind.
"""
from __future__ import annotations

import math
from typing import Dict

MAX_WEIGHT = 4.0     # no step is weighted more than 4x or less than 1/4 the geometric mean
MEMORY = 0.98        # G's running mean of log L: MEMORY * before + (1 - MEMORY) * this step's


class FrameBalance:
    """The running geometric mean loss per kind of step and the weights made of it."""

    def __init__(self, power: float, memory: float = MEMORY, max_weight: float = MAX_WEIGHT):
        if not (power >= 0.0 and math.isfinite(power)):
            raise ValueError(f"frame_balance power must be a finite number >= 0, got {power}")
        self.power, self.memory, self.max_weight = float(power), float(memory), float(max_weight)
        self.log_mean: Dict[str, float] = {}        # kind -> running mean of log L

    @property
    def enabled(self) -> bool:
        return self.power > 0.0

    def weight(self, kind: str, loss: float) -> float:
        """The weight of a step of this kind whose loss is ``loss``: 1 when disabled, for the
        kind's first step, or for a loss that is not finite and positive."""
        log_g = self.log_mean.get(kind)
        if not self.enabled or log_g is None or not (loss > 0.0 and math.isfinite(loss)):
            return 1.0
        w = math.exp(self.power * (log_g - math.log(loss)))
        return min(max(w, 1.0 / self.max_weight), self.max_weight)

    def update(self, kind: str, loss: float) -> None:
        """Fold a step's loss into its kind's running mean (non-finite or non-positive: skipped)."""
        if not (loss > 0.0 and math.isfinite(loss)):
            return
        old = self.log_mean.get(kind)
        x = math.log(loss)
        self.log_mean[kind] = x if old is None else self.memory * old + (1.0 - self.memory) * x
