"""The public render op: forward and adjoint of the whole splatting pipeline on the device.

    [select] -> project4d -> bin_and_sort (scan, bin, radix sort, ranges) -> rasterize
    LiveRows    Projected     Binned                                        RasterOut   (the stage records)

``select`` (optional, ops/select.py) first gathers the Gaussians that may be alive at t: the
later stages then run on those rows only, with the same per-Gaussian results.

``render`` returns a :class:`RenderOutput` holding the composited channels and the stage records
the adjoint needs; ``render_backward`` runs rasterize_bwd then project4d_bwd and returns the
gradient of every parameter (and, when given, accumulates the densification statistics).
Feature channels are ``[r, g, b, depth, flow_x, flow_y]`` (docs/ARCHITECTURE.md).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Dict, Optional

import numpy as np
import pyopencl.array as cla

from .camera import Camera
from .layout import CHANNELS, DEPTH, FLOW, RGB  # noqa: F401  (CHANNELS: read from here by callers)
from .ops.binning import bin_projected
from .ops.project import project4d, project4d_bwd
from .ops.rasterize import accumulate_densify_stats, rasterize_projected, rasterize_projected_bwd, simt_device
from .ops.select import SELECT_MAX_SHARE, select_live


@dataclass
class RenderOutput:
    features: object            # cla [H, W, C]: composited r, g, b, depth, flow_x, flow_y
    alpha: object               # cla [H, W]
    camera: Camera
    t: float
    t_flow: Optional[float]
    proj: object                # ops.project.Projected
    binned: object              # ops.binning.Binned: sorted_values, tile_ranges, n_isect, offsets
    raster: object              # ops.rasterize.RasterOut
    live: object = None         # ops.select.LiveRows when rendered with select=True, else None
    timings: Dict[str, float] = field(default_factory=dict)  # ms per stage when timed
    v_means2d: object = None    # cla [N, 2]: render_backward's screen-space gradient (accumulate_stats)

    @property
    def sorted_values(self):    # cla int32 [M]
        return self.binned.sorted_values

    @property
    def tile_ranges(self):      # cla int32 [n_tiles, 2]
        return self.binned.tile_ranges

    @property
    def offsets(self):          # cla int32 [N + 1] binning offsets (ops.binning.bin_gaussians)
        return self.binned.offsets

    @property
    def n_isect(self) -> int:   # M, number of (tile, Gaussian) pairs
        return int(self.binned.n_isect)

    @property
    def overflowed(self) -> bool:
        """The selected rows or the binning's pairs did not fit their buffers (render(check=False)
        only): not to be used."""
        return (self.live is not None and self.live.overflowed) or self.binned.overflowed

    def host(self) -> Dict[str, np.ndarray]:
        """Download: image [H,W,3], depth [H,W], flow [H,W,2], alpha [H,W] as numpy arrays."""
        f = self.features.get()
        return {"image": f[..., RGB], "depth": f[..., DEPTH], "flow": f[..., FLOW], "alpha": self.alpha.get()}


def _tick(rt, timings, name, t0, timed):
    if timed:
        rt.queue.finish()
        t1 = time.perf_counter()
        timings[name] = (t1 - t0) * 1e3
        return t1
    return t0


def render(rt, params: Dict[str, object], camera: Camera, t: float, t_flow: Optional[float] = None,
           timed: bool = False, select: bool = False, check: bool = True) -> RenderOutput:
    """Render the Gaussians at time ``t``; the flow channels hold the displacement to ``t_flow``.
    select: first gather the Gaussians that may be alive at t (ops/select.py; the same images)
    when they are at most SELECT_MAX_SHARE of them: the stage records (and render_backward's
    gradients) then have one row per selected Gaussian, out.live.rows naming them (out.live is
    None when every row was rendered).
    check: the selection reads its row count (ops/select.py) and the binning waits for its pair
    count and re-emits the pairs where they overflowed its buffers (ops/binning.py); check=False
    reads nothing, and the caller tests out.overflowed after its own next wait on the device (the
    training step's read-back) and renders again where it is true."""
    timings: Dict[str, float] = {}
    t0 = time.perf_counter()
    if timed:
        rt.queue.finish()
    live = None
    if select:
        live = select_live(rt, params, t, SELECT_MAX_SHARE, check=check)
        if live is not None:
            params = live.params
        t0 = _tick(rt, timings, "select", t0, timed)
    proj = project4d(rt, params, camera, t, t_flow, channels=CHANNELS)
    t0 = _tick(rt, timings, "project", t0, timed)
    binned = bin_projected(rt, proj, camera.width, camera.height, check=check)
    t0 = _tick(rt, timings, "bin_sort", t0, timed)
    raster = rasterize_projected(rt, proj, binned, camera.width, camera.height)
    _tick(rt, timings, "rasterize", t0, timed)
    if timed:
        timings["total"] = sum(timings.values())
    return RenderOutput(raster.out, raster.alpha, camera, t, t_flow, proj, binned, raster, live, timings)


def render_backward(rt, params: Dict[str, object], out: RenderOutput, v_features, v_alpha=None,
                    densify_stats: Optional[Dict[str, object]] = None, timed: bool = False,
                    deterministic: Optional[bool] = None, sh_factors: bool = False) -> Dict[str, object]:
    """Gradients of every parameter from the gradient images.

    v_features: cla [H, W, C] gradient of the loss w.r.t. the composited channels;
    v_alpha: cla [H, W] or None (zero); densify_stats: optional dict of device arrays
    grad_accum [N] f32, count [N] i32, max_radius [N] f32 updated in place.
    deterministic: bit-identical gradients across runs (per-entry terms summed in tile order
    instead of float atomics; see ops/rasterize.py). None: on for devices without a reported SIMT
    width (CPU drivers, where it is also the faster mode: benchmarks/bench_render.py times both), off
    on SIMT devices (GPUs), whose atomics are cheap.
    sh_factors: v_sh as an ops.project.ShGradFactors (its per-Gaussian factors; the training step
    passes it to DeviceAdam) instead of the full [N, NT+1, K, 3] array.
    A render with select=True: the gradients have one row per selected Gaussian ([L, ...], row i
    belonging to Gaussian out.live.rows[i]; every other Gaussian's gradient is 0), the densification
    statistics (still [N]) are updated at those rows.
    Returns {v_means, v_scales, v_quat_l, v_quat_r, v_opacity, v_sh, v_phase}.
    """
    cam = out.camera
    if deterministic is None:
        deterministic = not simt_device(rt)
    if v_alpha is None:
        # one zero image per size, kept by the runtime (the adjoint kernels only read v_alpha)
        v_alpha = rt.cached(("render.zero_v_alpha", cam.height, cam.width),
                            lambda: cla.zeros(rt.queue, (cam.height, cam.width), np.float32))
    t0 = time.perf_counter()
    if out.live is not None:
        params = out.live.params
    p = out.proj
    v2d = rasterize_projected_bwd(rt, p, out.binned, out.raster, v_features, v_alpha, cam.width, cam.height,
                                  deterministic=bool(deterministic))
    t0 = _tick(rt, out.timings, "rasterize_bwd", t0, timed)
    out.v_means2d = v2d["v_means2d"]
    if densify_stats is not None:
        accumulate_stats(rt, out, densify_stats)
    grads = project4d_bwd(rt, params, cam, out.t, out.t_flow, p, v2d["v_means2d"], v2d["v_conic"],
                          v2d["v_opac"], v2d["v_features"], sh_factors=sh_factors)
    _tick(rt, out.timings, "project_bwd", t0, timed)
    return grads


def accumulate_stats(rt, out: RenderOutput, densify_stats: Dict[str, object], skip=None) -> None:
    """The densification statistics of the render's adjoint (ops.rasterize.accumulate_densify_stats
    of out.v_means2d, which render_backward left): render_backward(densify_stats=...) calls it, and
    the training step calls it itself once it has seen that the render did not overflow, or with
    the step's gate (skip: ops.util.step_gate) before it knows."""
    if out.v_means2d is None:
        raise ValueError("accumulate_stats: render_backward has not run on this render")
    p, cam = out.proj, out.camera
    if int(p.radius.shape[0]):
        accumulate_densify_stats(rt, out.v_means2d, p.radius, cam.width, cam.height, densify_stats["grad_accum"],
                                 densify_stats["count"], densify_stats["max_radius"],
                                 rows=None if out.live is None else out.live.rows, skip=skip)
