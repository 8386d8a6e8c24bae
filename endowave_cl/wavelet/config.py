"""Settings of the rational-wavelet loss and its device entry point (the trainer's interface),
torch-free; loss.py re-exports both beside the torch implementation."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple

from .filters import rational_factor
from .ops import loss_and_grad

BORDERS = ("reflect",)


@dataclass
class WaveletConfig:
    """Settings of the rational-wavelet loss.

    q:       a = (q + 1) / q.  Default 2: a = 3/2, sigma = 2/3, 13 taps (R = 6), the smallest
             truly rational factor.  In research/tune_wavelet.py q = 1 (dyadic) and q = 2 tie within
             the seed noise (docs/WAVELET.md); q = 2 is kept as the paper's rational design.
    levels:  decomposition depth; the paper uses two.
    weights: (lambda_LL, lambda_LH, lambda_HL, lambda_HH), the weight of each band's mean squared
             coefficient error, the same at every level.  Default (0, 32, 32, 32): in the tuning
             experiment any LL weight lowered PSNR (the L1 term already fits low frequencies; LL
             of level 1 still feeds level 2's detail bands) and an overall detail weight of 16-64
             was best.  They are absolute, scaled so the term is of the order of an L1 image
             loss: add it to the colour loss (L1, or L1 mixed with D-SSIM) with weight 1.
    border:  "reflect": whole-sample symmetric extension (-1 -> 1, N -> N - 2) at every border;
             the only rule the kernels implement.
    """
    q: int = 2
    levels: int = 2
    weights: Tuple[float, float, float, float] = (0.0, 32.0, 32.0, 32.0)
    border: str = "reflect"

    def __post_init__(self):
        rational_factor(self.q)  # validates q
        if int(self.levels) < 1:
            raise ValueError(f"levels must be >= 1, got {self.levels}")
        self.weights = tuple(float(w) for w in self.weights)
        if len(self.weights) != 4:
            raise ValueError("weights must be (lambda_LL, lambda_LH, lambda_HL, lambda_HH)")
        if self.border not in BORDERS:
            raise ValueError(f"border must be one of {BORDERS}, got {self.border!r}")

    @property
    def a(self) -> float:
        p, q = rational_factor(self.q)
        return p / q


# ---------------------------------------------------------------------------------------------
# device entry point (the trainer's interface)
# ---------------------------------------------------------------------------------------------

def wavelet_loss_and_grad(rt, rendered, target, mask=None, config: WaveletConfig = WaveletConfig()):
    """(loss: float, v_rendered: cla.Array [H, W, C]) on the device.

    rendered, target: pyopencl arrays [H, W, C] float32 (any H, W, C); mask: [H, W] float32 or None.
    The mask multiplies both images before the transform; v_rendered already includes it.
    """
    return loss_and_grad(rt, rendered, target, mask, config.q, config.levels, config.weights)
