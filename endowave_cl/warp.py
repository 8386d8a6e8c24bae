"""Warps and splats of images along per-pixel displacements (numpy / OpenCV, no device): the ground
floor that the baselines (baselines.py), the flow checks (data/flow.py) and the in-between targets
(train/between.py) share."""
from __future__ import annotations

import functools
from typing import Optional

import cv2
import numpy as np


def warp_backward(image: np.ndarray, flow: np.ndarray, s: float) -> np.ndarray:
    """image sampled at p - s flow(p) (bilinear, border repeated): the frame moved a fraction s of
    the way along its flow."""
    return sample_displaced(image, -s * np.asarray(flow, np.float32))


# how sample_displaced interpolates between pixels: "linear" (bilinear; at a half-pixel offset it
# averages two neighbours, a low-pass), "cubic" (bicubic, a = -0.75: keeps more of the texture),
# "lanczos" (Lanczos-4, 8 x 8 taps at positions rounded to 1/32 pixel: sharper still)
SAMPLERS = {"linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC, "lanczos": cv2.INTER_LANCZOS4}


@functools.lru_cache(maxsize=8)
def _pixel_grid(h: int, w: int):
    """(u, v) [h, w] float32: each pixel's x and y, made once per size (read-only)."""
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    u.setflags(write=False)
    v.setflags(write=False)
    return u, v


def sample_displaced(image: np.ndarray, disp: np.ndarray, sampler: str = "linear") -> np.ndarray:
    """image [H, W(, K)] sampled at p + disp(p) (disp [H, W, 2], pixels (x, y); border repeated),
    float32.  sampler: a key of SAMPLERS; "cubic" and "lanczos" values are clipped to the image's own
    range (their kernels overshoot at edges)."""
    if sampler not in SAMPLERS:
        raise ValueError(f"sampler must be one of {', '.join(SAMPLERS)}, got {sampler!r}")
    u, v = _pixel_grid(*disp.shape[:2])
    mx, my = u + disp[..., 0], v + disp[..., 1]
    mx, my = (m if m.dtype == np.float32 else m.astype(np.float32) for m in (mx, my))
    image = np.asarray(image, np.float32)
    out = cv2.remap(image, mx, my, SAMPLERS[sampler], borderMode=cv2.BORDER_REPLICATE)
    if sampler != "linear" and image.size:
        np.clip(out, image.min(), image.max(), out=out)
    return out


def splat_forward(image: np.ndarray, disp: np.ndarray, weight: Optional[np.ndarray] = None):
    """(num [H, W, C], den [H, W]) float32: every pixel p of image [H, W, C] pushed to p + disp(p)
    (disp [H, W, 2], pixels (x, y)) and shared among the four pixels around it with bilinear
    weights, times weight(p) ([H, W] or None: 1); num sums weight x colour, den the weights, so
    num / den is the splatted image where den > 0 (forward warping: the pixels of the target that
    no source pixel reaches have den 0, where a backward warp would invent them)."""
    h, w = disp.shape[:2]
    img = np.asarray(image, np.float32).reshape(h * w, -1)                              # [HW, C]
    u, v = _pixel_grid(h, w)
    x, y = (u + disp[..., 0]).ravel(), (v + disp[..., 1]).ravel()                       # [HW]
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = x - x0, y - y0
    # a source pixel reaches the image when its corner (x0, y0) lies in [-1, w - 1] x [-1, h - 1]:
    # the others (and non-finite motion) go to one spare bin past the canvas; the four corners land
    # on a canvas one pixel wider on every side, so that no corner needs its own bounds test
    reach = (x0 >= -1) & (x0 <= w - 1) & (y0 >= -1) & (y0 <= h - 1)
    cw = w + 2
    size = (h + 2) * cw
    # corner (x0, y0)'s index on the canvas, exact in float32 (size < 2^24); the spare bin where
    # the pixel reaches nothing
    if size >= 1 << 24:
        raise ValueError(f"splat_forward: {w}x{h} is too large an image")
    lin = (y0 + 1) * cw + (x0 + 1)
    lin[~reach] = size
    i00 = lin.astype(np.int64)
    idx = np.empty((4, h * w), np.int64)                                                # [4, HW]
    idx[0] = i00
    for k, off in ((1, 1), (2, cw), (3, cw + 1)):
        np.add(i00, off, out=idx[k])
    idx[1:, ~reach] = size
    gx, gy = 1 - fx, 1 - fy
    wts = np.empty((4, h * w), np.float64)                                              # [4, HW]
    for k, (a, b) in enumerate(((gx, gy), (fx, gy), (gx, fy), (fx, fy))):
        np.multiply(a, b, out=wts[k])          # the float32 product, stored as float64
    if weight is None:
        wts[:, ~reach] = 0.0
    else:
        wts *= np.where(reach, np.asarray(weight, np.float32).ravel(), 0)
    wts[~np.isfinite(wts)] = 0.0
    idx = idx.ravel()
    den = np.bincount(idx, wts.ravel(), size + 1)[:size]
    term = np.empty_like(wts)
    cols = []
    for c in range(img.shape[1]):
        np.multiply(wts, img[:, c], out=term)
        cols.append(np.bincount(idx, term.ravel(), size + 1)[:size])
    num = np.stack(cols, -1)
    crop = (slice(1, h + 1), slice(1, w + 1))
    return (num.reshape(h + 2, cw, -1)[crop].astype(np.float32),
            den.reshape(h + 2, cw)[crop].astype(np.float32))


def two_flow_displacements(f01: np.ndarray, f10: np.ndarray, t: float):
    """(d_t0, d_t1) [H, W, 2]: where the pixels of the frame at fraction t between frames 0 and 1
    are found in frame 0 and in frame 1, from both flows (f01: 0 -> 1, f10: 1 -> 0), as Super
    SloMo (Jiang et al., CVPR 2018) approximates them: d_t0 = -(1 - t) t f01 + t^2 f10,
    d_t1 = (1 - t)^2 f01 - t (1 - t) f10.  Where f10 = -f01 this is warp_backward's -t f01 and
    (1 - t) f01; where the two disagree it averages them, weighted by the nearer frame."""
    f01, f10 = np.asarray(f01, np.float32), np.asarray(f10, np.float32)
    return (-(1.0 - t) * t * f01 + t * t * f10), ((1.0 - t) ** 2 * f01 - t * (1.0 - t) * f10)
