"""The in-between target's stages on the device (cl/between_*.cl): the frames warped backward
along a path, the hypotheses fused, a path splatted forward and the frames pushed along it, the
model's prediction mixed in.  Each kernel's reference is the host path it replaces
(reference/between.py, which calls train/between.py and warp.py); train/between.py chains them
(DeviceTarget).  The targets are constants of the loss: no stage has an adjoint.

Shapes: frames [H, W, 4] (RGB and tool mask, frame_on_device), images [H, W, 3], masks and weights
[H, W], float32 device arrays (pyopencl), paths given
as a Path: g = ca A (+ cb B) with A, B device arrays of H x W pixels of ``pitch`` floats each,
the path's two components at ``offset`` (a render's feature image serves as it is).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import pyopencl.array as cla

from .util import WORK_GROUP, f32_literal

# between_splat's fixed point: sums in units of 2^-SPLAT_FRAC_BITS (64-bit integers; a weight of
# 1 is 2^32 units, so displacements up to 2^31 px and ~2^30 pixels landing on one pixel fit)
SPLAT_FRAC_BITS = 32
MAX_HYPOTHESES = 8       # between_fuse's most hypotheses (its per-pixel error array)
INT64_ATOMICS = "cl_khr_int64_base_atomics"
# the colour samplers of between_warp and between_push (warp.SAMPLERS' names) and their build options
# (cl/between_sample.h)
SAMPLER_OPTIONS = {"cubic": [], "lanczos": ["-DLANCZOS4"]}


@dataclass
class Path:
    """g(p) = ca A(p) (+ cb B(p)): A, B device arrays read at pixel p's floats offset, offset + 1 of
    a row of pitch floats."""
    a: object
    ca: float
    b: Optional[object] = None
    cb: float = 0.0
    pitch_a: int = 2
    offset_a: int = 0
    pitch_b: int = 2
    offset_b: int = 0

    def args(self, rt):
        b = self.a if self.b is None else self.b
        return [self.a.data, np.int32(self.pitch_a), np.int32(self.offset_a), np.float32(self.ca),
                b.data, np.int32(self.pitch_b if self.b is not None else self.pitch_a),
                np.int32(self.offset_b if self.b is not None else self.offset_a), np.float32(self.cb),
                np.int32(self.b is not None)]


@dataclass
class Frame:
    """A frame as the stages read it: image [H, W, 4] device array (RGB and the tool mask, 1 without
    one: frame_on_device), its colour's range (np.min, np.max: the bicubic samples are clipped to
    it, as warp.sample_displaced does), and whether it has a mask."""
    image: object
    lo: float
    hi: float
    has_mask: bool = False


def frame_on_device(rt, image: np.ndarray, mask: Optional[np.ndarray] = None) -> Frame:
    """A Frame of image [H, W, 3] and mask [H, W] (or None), uploaded."""
    image = np.asarray(image, np.float32)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"between: a frame image must be [H, W, 3], got {image.shape}")
    if mask is not None and np.shape(mask) != image.shape[:2]:
        raise ValueError(f"between: a frame mask must be [H, W] = {image.shape[:2]}, got {np.shape(mask)}")
    packed = np.ones(image.shape[:2] + (4,), np.float32)                              # [H, W, 4]
    packed[..., :3] = image
    if mask is not None:
        packed[..., 3] = mask
    return Frame(cla.to_device(rt.queue, packed), float(image.min()), float(image.max()), mask is not None)


def _size(frame: Frame):
    h, w = (int(v) for v in frame.image.shape[:2])
    if frame.image.shape != (h, w, 4):
        raise ValueError(f"between: a Frame's image must be [H, W, 4] (frame_on_device), got {tuple(frame.image.shape)}")
    return h, w


def _sampler_options(sampler: str):
    if sampler not in SAMPLER_OPTIONS:
        raise ValueError(f"between: sampler must be one of {', '.join(SAMPLER_OPTIONS)}, got {sampler!r}")
    return SAMPLER_OPTIONS[sampler]


def between_warp(rt, f0: Frame, f1: Frame, g0: Path, g1: Path, wa: float, wb: float, out=None,
                 sampler: str = "cubic"):
    """(blend [H, W, 3], diff [H, W], ok [H, W]): f0 sampled at p - g0(p) and f1 at p - g1(p)
    (the colour by sampler, a key of SAMPLER_OPTIONS, as train/between.py SAMPLER names it: W0, W1);
    blend = wa W0 + wb W1, diff = sum_c |W0 - W1|, ok = 1 where both warped masks show tissue
    (cl/between_warp.cl).  out: (blend, diff, ok) arrays to write instead of new ones."""
    h, w = _size(f0)
    opts = _sampler_options(sampler)
    if out is None:
        out = (rt.empty((h, w, 3)), rt.empty((h, w)), rt.empty((h, w)))
    k = rt.kernel("between_warp.cl", "between_warp", opts)
    rt.launch_1d(k, h * w, WORK_GROUP, f0.image.data, f1.image.data, np.float32(f0.lo), np.float32(f0.hi),
                 np.float32(f1.lo), np.float32(f1.hi), np.int32(f0.has_mask), np.int32(f1.has_mask),
                 *g0.args(rt), *g1.args(rt),
                 np.int32(w), np.int32(h), np.float32(wa), np.float32(wb), *(a.data for a in out))
    return out


def between_fuse(rt, blend, diff, ok, radius: int, tau: float, mode: str = "agree"):
    """(image [H, W, 3], weight [H, W]): K hypotheses (blend [K, H, W, 3], diff and ok [K, H, W],
    between_warp's) fused per pixel as train/between.py fused_interpolation (mode "agree": weights
    by the box mean of diff over (2 radius + 1)^2 pixels, falling by e per tau; "mean": equal
    weights over the ok ones) (cl/between_fuse.cl)."""
    K, h, w = (int(v) for v in diff.shape)
    if not 1 <= K <= MAX_HYPOTHESES:
        raise ValueError(f"between_fuse: 1 to {MAX_HYPOTHESES} hypotheses, got {K}")
    if mode not in ("agree", "mean"):
        raise ValueError(f"between_fuse: mode must be agree or mean, got {mode!r}")
    opts = [f"-DFUSE_RADIUS={int(radius)}", f"-DFUSE_TAU_INV={f32_literal(1.0 / tau)}",
            f"-DMAX_K={MAX_HYPOTHESES}"] + (["-DAGREE"] if mode == "agree" else [])
    image, weight = rt.empty((h, w, 3)), rt.empty((h, w))
    rows = diff
    if mode == "agree":
        rows = rt.empty((K, h, w))
        rt.launch_1d(rt.kernel("between_fuse.cl", "between_box_rows", opts), K * h * w, WORK_GROUP, diff.data,
                     np.int32(K), np.int32(w), np.int32(h), rows.data)
    rt.launch_1d(rt.kernel("between_fuse.cl", "between_fuse", opts), h * w, WORK_GROUP, blend.data, rows.data,
                 ok.data, np.int32(K), np.int32(w), np.int32(h), image.data, weight.data)
    return image, weight


def check_int64_atomics(rt) -> None:
    """One-line error where the device lacks the 64-bit integer atomics between_splat needs."""
    if INT64_ATOMICS not in rt.device.extensions:
        raise RuntimeError(f"between_splat: device {rt.name} lacks {INT64_ATOMICS}, which the in-between "
                           f"target's splat needs")


def between_splat(rt, g: Path, frame: Frame, acc=None):
    """acc [H, W, 3] int64: every pixel p (not a tool pixel of frame) splatted forward to p + g(p)
    with bilinear weights, as fixed-point sums of (weight, weight x -g) in units of
    2^-SPLAT_FRAC_BITS (cl/between_splat.cl; deterministic in every order)."""
    check_int64_atomics(rt)
    h, w = _size(frame)
    if acc is None:
        acc = rt.empty((h, w, 3), np.int64)
    rt.cl.enqueue_fill_buffer(rt.queue, acc.data, np.int64(0), 0, acc.nbytes)
    k = rt.kernel("between_splat.cl", "between_splat", [f"-DSPLAT_FRAC_BITS={SPLAT_FRAC_BITS}"])
    rt.launch_1d(k, h * w, WORK_GROUP, *g.args(rt), frame.image.data, np.int32(frame.has_mask), np.int32(w),
                 np.int32(h), acc.data)
    return acc


def between_push(rt, acc0, acc1, f0: Frame, f1: Frame, wa: float, wb: float, fill, min_weight: float,
                 sampler: str = "cubic"):
    """[H, W, 3]: frames f0 and f1 pushed along the paths splatted into acc0 and acc1 (between_splat;
    the colour sampled by sampler, as between_warp) and blended with weights wa min(reach0, 1) and
    wb min(reach1, 1) where each reach is above min_weight; fill where their sum is not
    (cl/between_push.cl, train/between.py reversed_splat_interpolation)."""
    h, w = _size(f0)
    out = rt.empty((h, w, 3))
    opts = [f"-DSPLAT_FRAC_BITS={SPLAT_FRAC_BITS}", f"-DSPLAT_MIN_WEIGHT={f32_literal(min_weight)}",
            *_sampler_options(sampler)]
    rt.launch_1d(rt.kernel("between_push.cl", "between_push", opts), h * w, WORK_GROUP, acc0.data, acc1.data,
                 f0.image.data, f1.image.data, np.float32(f0.lo), np.float32(f0.hi), np.float32(f1.lo),
                 np.float32(f1.hi), np.float32(wa), np.float32(wb), np.int32(w), np.int32(h), fill.data, out.data)
    return out


def between_mix(rt, flow, weight, model=None, model_weight: float = 0.0, ok=None):
    """(image [H, W, 3], weight [H, W], count int32 [1]): the flow prediction (flow, weight) blended
    with the model's, (1 - model_weight) flow + model_weight model, the weight times ok; without a
    model, the flow prediction as it is.  count: the pixels whose weight is above 0 (for the
    loss's denominator; cl/between_mix.cl)."""
    h, w = (int(v) for v in weight.shape)
    image, weight_out = rt.empty((h, w, 3)), rt.empty((h, w))
    count = rt.empty((1,), np.int32)
    rt.cl.enqueue_fill_buffer(rt.queue, count.data, np.int32(0), 0, 4)
    wm = float(model_weight) if model is not None else 0.0
    rt.launch_1d(rt.kernel("between_mix.cl", "between_mix"), h * w, WORK_GROUP, flow.data,
                 (model if model is not None else flow).data, np.float32(1.0 - wm), np.float32(wm), weight.data,
                 rt.buf(ok), np.int32(ok is not None), np.int32(h * w), image.data, weight_out.data, count.data,
                 rt.cl.LocalMemory(4))
    return image, weight_out, count


def stack(rt, arrays: Sequence[object]):
    """The device arrays (one shape) stacked along a new first axis, copied on the device."""
    first = arrays[0]
    out = rt.empty((len(arrays),) + tuple(first.shape), first.dtype)
    for i, a in enumerate(arrays):
        rt.cl.enqueue_copy(rt.queue, out.data, a.data, byte_count=int(a.nbytes), dst_offset=i * int(a.nbytes),
                           src_offset=int(a.offset))
    return out
