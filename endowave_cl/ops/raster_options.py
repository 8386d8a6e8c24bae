"""The rasterizer's build options and variant record, below both the rasterizer ops
(ops/rasterize.py) and the probe that checks a variant before this process builds it (probe.py,
which keys its verdicts by these options)."""
from __future__ import annotations

from dataclasses import dataclass

from ..layout import ALPHA_MAX, ALPHA_MIN, T_STOP
from .util import f32_literal


def _options(C: int):
    return [f"-DC={int(C)}", f"-DALPHA_MAX={f32_literal(ALPHA_MAX)}",
            f"-DALPHA_MIN={f32_literal(ALPHA_MIN)}", f"-DT_STOP={f32_literal(T_STOP)}"]


@dataclass(frozen=True)
class RasterChoice:
    """The rasterizer variant a call runs: "scalar", or "vector" with vw lanes in bw-wide blocks."""
    variant: str
    vw: int = 0
    bw: int = 0

    def describe(self) -> str:
        return "scalar kernel" if self.variant == "scalar" else f"vector kernel, {self.vw} lanes"


def vec_options(C: int, ch: RasterChoice):
    """Build options of rasterize_vec.cl for C channels and the variant ch."""
    return _options(C) + [f"-DVW={ch.vw}", f"-DBW={ch.bw}"]
