"""The training step's image losses on the device (kernels in cl/image_loss.cl).

``image_losses_and_grad`` computes what ``reference/losses.py::image_losses_ref`` (the torch reference, whose module
doc gives the definitions and choices) computes, plus the rational-wavelet term, from the rendered
feature image that stays on the device, and returns the gradient image for the adjoints: nothing
but a handful of loss sums crosses to the host.

    feat [H, W, CF] --ssim_stack--> maps [H, W, 9] --blur W, H--> blurred
          |                                                            |
          +------------------- image_loss_terms <----------------------+ <-- target's blurred maps
                  |  v_feat (L1, depth, flow)    g_ssim [H, W, 9]            [H, W, 6] (per frame,
                  |                                 |  blur adjoint          prepare_targets)
                  +------ ssim_grad_combine <-------+
                          + lambda_wavelet * m * v_rgb (wavelet.diff_loss_and_grad_deferred
                            on rgb_masked_diff(feat, target)), in the same pass
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Dict, Optional, Tuple

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from ..runtime import round_up
from ..loss_constants import gaussian_window_1d
from ..ops.util import read_back
from ..wavelet.ops import conv_axis, diff_loss_and_grad_deferred

KFILE = "image_loss.cl"
LOCAL = 64          # work-group size of the per-pixel kernels (power of two: image_loss_terms reduces)
NMAP, NTMAP, NGRAD, NSUM = 9, 6, 9, 5   # as in cl/image_loss.cl


@dataclass
class DeviceTargets:
    """One frame's supervision on the device, with the per-frame weight maps and their sums."""
    image: object                 # cla [H, W, 3]
    mask: object                  # cla [H, W]: 1 = supervise (all ones without a tool mask)
    has_mask: bool
    n_rgb: Optional[float]        # 3 * sum(mask): the colour terms' denominator (at least 1)
    depth: Optional[object]       # cla [H, W] or None
    depth_w: Optional[object]     # cla [H, W]: (depth > 0) * mask
    n_depth: float
    flow: Optional[object]        # cla [H, W, 2] or None
    flow_w: Optional[object]      # cla [H, W]: consistency mask * mask
    n_flow: float
    ssim_target: Optional[object] = None   # cla [H, W, NTMAP]: the blurred (y m, (y m)^2), per frame
    supervised: Optional[object] = None    # cla int32 [1]: sum(mask) where only the device knows it
                                           # (device_targets; n_rgb is then None until read back)


def prepare_targets(rt, image: np.ndarray, mask: Optional[np.ndarray] = None, depth: Optional[np.ndarray] = None,
                    flow: Optional[np.ndarray] = None, flow_valid: Optional[np.ndarray] = None,
                    temporary: bool = False) -> DeviceTargets:
    """Upload a frame's targets (numpy, channel-last) with the weight maps of image_losses_ref (reference/losses.py).
    temporary: targets of one step (an in-between frame): device memory from the runtime's pool, and
    uploads that do not wait (each keeps its host array alive until it is done)."""
    allocator = rt.pool() if temporary else None

    def up(a):
        return cla.to_device(rt.queue, np.ascontiguousarray(a, np.float32), allocator=allocator, async_=temporary)

    H, W = image.shape[:2]
    m = np.ones((H, W), np.float32) if mask is None else np.asarray(mask, np.float32)
    t = DeviceTargets(up(image), up(m), mask is not None, max(3.0 * float(m.sum(dtype=np.float64)), 1.0),
                      None, None, 1.0, None, None, 1.0)
    if depth is not None:
        dw = (np.asarray(depth) > 0).astype(np.float32) * m
        t.depth, t.depth_w, t.n_depth = up(depth), up(dw), max(float(dw.sum(dtype=np.float64)), 1.0)
    if flow is not None:
        fw = m if flow_valid is None else np.asarray(flow_valid, np.float32) * m
        t.flow, t.flow_w, t.n_flow = up(flow), up(fw), max(float(fw.sum(dtype=np.float64)), 1.0)
    t.ssim_target = _ssim_target(rt, t.image, t.mask, allocator)
    return t


def device_targets(rt, image, weight, supervised) -> DeviceTargets:
    """The DeviceTargets of an image [H, W, 3] and a 0 / 1 weight [H, W] made on the device (an
    in-between target, train/between_device.py), as prepare_targets(rt, image, weight,
    temporary=True) makes them from host arrays; supervised: the pixels whose weight is 1, an int
    or an int32 [1] device array left there (the losses then take the colour terms' weights from
    rgb_weight_table on the device and read the count back with their sums)."""
    on_device = not isinstance(supervised, (int, np.integer))
    n_rgb = None if on_device else rgb_denominator(supervised)
    t = DeviceTargets(image, weight, True, n_rgb, None, None, 1.0, None, None, 1.0,
                      supervised=supervised if on_device else None)
    t.ssim_target = _ssim_target(rt, t.image, t.mask, rt.pool())
    return t


def rgb_denominator(supervised: int) -> float:
    """n_rgb of a 0 / 1 mask with this many supervised pixels: 3 of them per pixel, at least 1."""
    return max(3.0 * float(supervised), 1.0)


def rgb_weights(cfg, n_rgb):
    """(w_l1, w_ssim) of image_loss_terms as float32: lambda_rgb (1 - lambda_dssim) / n_rgb and
    lambda_rgb lambda_dssim / n_rgb, in float64 and rounded once (n_rgb a float or a float64 array)."""
    w_rgb = cfg.lambda_rgb / n_rgb
    return np.float32(w_rgb * (1.0 - cfg.lambda_dssim)), np.float32(w_rgb * cfg.lambda_dssim)


def rgb_weight_table(rt, cfg, npix: int):
    """cla float32 [npix + 1, 2]: rgb_weights for every supervised pixel count 0 .. npix (the same
    float64 operations, elementwise), for targets whose count stays on the device; per runtime,
    lambdas and size."""

    def make():
        w_l1, w_ssim = rgb_weights(cfg, np.maximum(3.0 * np.arange(npix + 1, dtype=np.float64), 1.0))
        return cla.to_device(rt.queue, np.ascontiguousarray(np.stack([w_l1, w_ssim], 1), np.float32))
    return rt.cached(("image_loss.rgb_weights", float(cfg.lambda_rgb), float(cfg.lambda_dssim), int(npix)), make)


def _ssim_target(rt, image, mask, allocator=None) -> object:
    """The target's SSIM maps (y m, (y m)^2) blurred: they do not depend on the render, so they are
    made once per frame here instead of in every step."""
    H, W = (int(s) for s in image.shape[:2])
    npix = H * W
    stack = rt.empty((H, W, NTMAP), np.float32)
    rt.launch(rt.kernel(KFILE, "ssim_target_stack"), (round_up(max(npix, 1), LOCAL),), (LOCAL,), image.data,
              mask.data, np.int32(npix), stack.data)
    window = _window(rt)
    tmp = conv_axis(rt, stack, window, axis=1, border="zero")
    out = cla.empty(rt.queue, (H, W, NTMAP), np.float32, allocator=allocator)   # None: own buffer, kept for the run
    return conv_axis(rt, tmp, window, axis=0, out=out, border="zero")


def _window(rt) -> object:
    """The SSIM window (loss_constants.gaussian_window_1d) as a float32 device array, cached per runtime."""
    # symmetric: its own reverse
    return rt.cached("ssim.window", lambda: cla.to_device(rt.queue, gaussian_window_1d().astype(np.float32)))


def _blur(rt, x, window) -> object:
    """The separable SSIM blur (zero padding) of x [H, W, K]: along W, then along H."""
    return conv_axis(rt, conv_axis(rt, x, window, axis=1, border="zero"), window, axis=0, border="zero")


@dataclass
class PendingLosses:
    """The losses of one step, enqueued on the device: the gradient image, the device sums the loss
    values are made of, and how the host finishes them once it has read the sums back."""
    v_features: object                 # cla [H, W, CF]: d total / d features
    sums: Dict[str, object]            # "image": cla [groups, NSUM] f32; "wavelet": cla [partial sums] f32
    finish: Callable[[Dict[str, np.ndarray]], Tuple[float, Dict[str, float]]]   # host sums -> (total, parts)


def image_losses_and_grad(rt, features, tgt: DeviceTargets, cfg, channels: Dict[str, int],
                          wavelet_config=None) -> Tuple[float, Dict[str, float], object]:
    """(total loss, its parts, v_features [H, W, CF]) for the rendered features [H, W, CF] (cla).

    cfg: a TrainConfig (lambda_*, use_depth, use_flow, use_wavelet); channels: {"depth": k,
    "flow": k} (the colour is channels 0..2).  Terms whose targets are missing are left out, as
    in image_losses_ref (reference/losses.py).  parts: l1, ssim, rgb, [depth], [flow], [wavelet], total, psnr.
    Reads the sums back (one read); the trainer uses image_losses_enqueue and reads them with the
    step's other scalars.
    """
    pending = image_losses_enqueue(rt, features, tgt, cfg, channels, wavelet_config)
    total, parts = pending.finish(read_back(rt, pending.sums))
    return total, parts, pending.v_features


def image_losses_enqueue(rt, features, tgt: DeviceTargets, cfg, channels: Dict[str, int],
                         wavelet_config=None) -> PendingLosses:
    """image_losses_and_grad without the read-back: the kernels are enqueued, nothing is read."""
    if features.ndim != 3 or features.dtype != np.float32:
        raise ValueError(f"features must be a float32 [H, W, C] array, got {features.dtype} {features.shape}")
    H, W, CF = (int(s) for s in features.shape)
    if tuple(tgt.image.shape) != (H, W, 3):
        raise ValueError(f"target image {tuple(tgt.image.shape)} does not match the rendered {H}x{W}")
    if CF < 3 or not (3 <= channels["depth"] < CF and 3 <= channels["flow"] and channels["flow"] + 1 < CF):
        raise ValueError(f"channels {channels} do not fit the {CF} rendered channels (colour in 0..2)")
    npix = H * W
    opts = [f"-DCF={CF}", f"-DCH_DEPTH={int(channels['depth'])}", f"-DCH_FLOW={int(channels['flow'])}"]
    use_depth = bool(cfg.use_depth and cfg.lambda_depth > 0 and tgt.depth is not None)
    use_flow = bool(cfg.use_flow and cfg.lambda_flow > 0 and tgt.flow is not None)
    window = _window(rt)
    gsize = (round_up(max(npix, 1), LOCAL),)

    maps = rt.empty((H, W, NMAP), np.float32)
    rt.launch(rt.kernel(KFILE, "ssim_stack", opts), gsize, (LOCAL,), features.data, tgt.image.data, tgt.mask.data,
              np.int32(npix), maps.data)
    blurred = _blur(rt, maps, window)

    v = rt.empty((H, W, CF), np.float32)
    g_ssim = rt.empty((H, W, NGRAD), np.float32)
    groups = gsize[0] // LOCAL
    partial = rt.empty((groups, NSUM), np.float32)
    on_device = tgt.supervised is not None     # the count (and n_rgb) known on the device only
    w_l1, w_ssim = (np.float32(0), np.float32(0)) if on_device else rgb_weights(cfg, tgt.n_rgb)
    dummy = tgt.mask.data
    rt.launch(
        rt.kernel(KFILE, "image_loss_terms", opts), gsize, (LOCAL,),
        features.data, tgt.image.data, tgt.mask.data, blurred.data, tgt.ssim_target.data,
        tgt.depth.data if use_depth else dummy, tgt.depth_w.data if use_depth else dummy,
        tgt.flow.data if use_flow else dummy, tgt.flow_w.data if use_flow else dummy,
        np.int32(use_depth), np.int32(use_flow),
        w_l1, w_ssim,
        np.float32(cfg.lambda_depth / tgt.n_depth), np.float32(cfg.lambda_flow / tgt.n_flow),
        np.float32(cfg.flow_huber_delta), np.int32(npix),
        v.data, g_ssim.data, partial.data, cl.LocalMemory(4 * NSUM * LOCAL), np.int32(on_device),
        tgt.supervised.data if on_device else dummy, rgb_weight_table(rt, cfg, npix).data if on_device else dummy)
    gb = _blur(rt, g_ssim, window)   # the blur's adjoint: same separable window (symmetric), zero border

    sums = {"image": partial}
    if on_device:
        sums["supervised"] = tgt.supervised
    wavelet_finish = None
    v_rgb = None
    if cfg.use_wavelet and cfg.lambda_wavelet > 0 and wavelet_config is not None:
        d = rt.empty((H, W, 3), np.float32)
        rt.launch(rt.kernel(KFILE, "rgb_masked_diff", opts), gsize, (LOCAL,), features.data, tgt.image.data,
                  tgt.mask.data, np.int32(tgt.has_mask), np.int32(npix), d.data)
        sums["wavelet"], wavelet_finish, v_rgb = diff_loss_and_grad_deferred(
            rt, d, wavelet_config.q, wavelet_config.levels, wavelet_config.weights)
    # the SSIM gradient through the maps, and lambda_wavelet * m * v_rgb, into v
    rt.launch(rt.kernel(KFILE, "ssim_grad_combine", opts), gsize, (LOCAL,), features.data, tgt.image.data,
              tgt.mask.data, gb.data, np.int32(npix), v.data, np.int32(v_rgb is not None), np.int32(tgt.has_mask),
              np.float32(cfg.lambda_wavelet), rt.buf(v_rgb))

    def finish(host: Dict[str, np.ndarray]) -> Tuple[float, Dict[str, float]]:
        s = host["image"].astype(np.float64).sum(axis=0)   # [NSUM]
        n_rgb = rgb_denominator(int(host["supervised"][0])) if on_device else tgt.n_rgb
        l1, ssim = s[0] / n_rgb, s[1] / n_rgb
        rgb_loss = (1.0 - cfg.lambda_dssim) * l1 + cfg.lambda_dssim * (1.0 - ssim)
        total = cfg.lambda_rgb * rgb_loss
        parts: Dict[str, float] = dict(l1=float(l1), ssim=float(ssim), rgb=float(rgb_loss))
        if use_depth:
            parts["depth"] = float(s[2] / tgt.n_depth)
            total += cfg.lambda_depth * parts["depth"]
        if use_flow:
            parts["flow"] = float(s[3] / tgt.n_flow)
            total += cfg.lambda_flow * parts["flow"]
        if wavelet_finish is not None:
            wavelet = wavelet_finish(host["wavelet"])
            parts["wavelet"] = float(wavelet)
            total += cfg.lambda_wavelet * wavelet
        parts["total"] = float(total)
        mse = s[4] / n_rgb
        parts["psnr"] = float(10.0 * np.log10(1.0 / max(mse, 1e-12)))
        return float(total), parts

    return PendingLosses(v, sums, finish)
