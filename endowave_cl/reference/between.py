"""References of the in-between target's device stages (ops/between.py, cl/between_*.cl): the host
path they replace (numpy and OpenCV: warp.py, train/between.py), stage by stage, on host arrays.

Paths are given as host arrays g [H, W, 2] (the ops' Path evaluated: ca A + cb B)."""
from __future__ import annotations

from typing import Optional, Sequence

import cv2
import numpy as np

from ..warp import sample_displaced, splat_forward


def between_warp_ref(img0: np.ndarray, img1: np.ndarray, g0: np.ndarray, g1: np.ndarray, wa: float, wb: float,
                     mask0: Optional[np.ndarray] = None, mask1: Optional[np.ndarray] = None, sampler: str = "cubic"):
    """(blend [H, W, 3], diff [H, W], ok [H, W]) float32: img0 at p - g0 and img1 at p - g1 (W0, W1,
    the colour by sampler (warp.SAMPLERS), as train/between.py _warp_pair samples them); blend = wa W0
    + wb W1, diff = sum_c |W0 - W1|, ok = 1 where both masks sampled bilinearly exceed 0.5."""
    w0 = sample_displaced(img0, -np.asarray(g0, np.float32), sampler)
    w1 = sample_displaced(img1, -np.asarray(g1, np.float32), sampler)
    ok = np.ones(w0.shape[:2], np.float32)
    for m, g in ((mask0, g0), (mask1, g1)):
        if m is not None:
            ok *= (sample_displaced(np.asarray(m, np.float32), -np.asarray(g, np.float32)) > 0.5).astype(np.float32)
    blend = (np.float32(wa) * w0 + np.float32(wb) * w1).astype(np.float32)
    diff = np.abs(w0 - w1).sum(-1, dtype=np.float32)
    return blend, diff, ok


def between_fuse_ref(blend: np.ndarray, diff: np.ndarray, ok: np.ndarray, radius: int, tau: float,
                     mode: str = "agree"):
    """(image [H, W, 3], weight [H, W]): train/between.py fused_interpolation on hypotheses given by
    their blends [K, H, W, 3], their warps' channel-summed differences diff [K, H, W] and ok
    [K, H, W]."""
    if mode == "mean":
        err = np.zeros(diff.shape, np.float32)
    else:
        size = (2 * radius + 1,) * 2
        err = np.stack([cv2.blur(np.asarray(d, np.float32), size) for d in diff])             # [K, H, W]
    good = np.asarray(ok) > 0
    any_ok = good.any(0)
    good |= ~any_ok
    err[~good] = np.inf
    w = np.exp((err.min(0) - err) * np.float32(1.0 / tau))
    w /= w.sum(0)
    image = np.zeros(blend.shape[1:], np.float32)
    for wk, b in zip(w, blend):
        image += wk[..., None] * b
    return image, any_ok.astype(np.float32)


def between_splat_ref(g: np.ndarray, mask: Optional[np.ndarray] = None):
    """(den [H, W], num [H, W, 2]): every pixel splatted forward along g with bilinear weights
    (warp.splat_forward of -g along g, tool pixels left out), as train/between.py reversed_splat
    splats a path."""
    g = np.asarray(g, np.float32)
    weight = None if mask is None else (np.asarray(mask) > 0.5).astype(np.float32)
    num, den = splat_forward(-g, g, weight)
    return den, num


def between_push_ref(img0: np.ndarray, img1: np.ndarray, splat0, splat1, wa: float, wb: float,
                     fill: np.ndarray, min_weight: float, sampler: str = "cubic") -> np.ndarray:
    """[H, W, 3]: train/between.py reversed_splat_interpolation's image from the two frames' splats
    ((den, num) each, between_splat_ref): each frame sampled (by sampler) where its splat says q's
    colour comes from, blended by wa min(reach0, 1) and wb min(reach1, 1) where each reach exceeds
    min_weight, fill where their sum does not."""
    image = np.zeros(fill.shape, np.float32)
    total = np.zeros(fill.shape[:2], np.float32)
    for img, (den, num), a in ((img0, splat0, wa), (img1, splat1, wb)):
        ok = den > min_weight
        back = np.zeros(num.shape, np.float32)
        back[ok] = num[ok] / den[ok][:, None]
        pushed = sample_displaced(img, back, sampler)
        wt = np.where(ok, np.float32(a) * np.minimum(den, np.float32(1)), np.float32(0))
        image += wt[..., None] * pushed
        total += wt
    out = np.array(fill, np.float32, copy=True)
    reach = total > min_weight
    out[reach] = image[reach] / total[reach][:, None]
    return out


def between_mix_ref(flow: np.ndarray, weight: np.ndarray, model: Optional[np.ndarray] = None,
                    model_weight: float = 0.0, ok: Optional[np.ndarray] = None):
    """(image, weight, count): train/between.py blend_model_prediction's end,
    (1 - model_weight) flow + model_weight model and weight x ok; the pixels with weight > 0."""
    image = np.asarray(flow, np.float32)
    if model is not None and model_weight != 0.0:
        image = (np.float32(1.0 - model_weight) * image + np.float32(model_weight) * model).astype(np.float32)
    w = np.asarray(weight, np.float32) * (1.0 if ok is None else np.asarray(ok, np.float32))
    return image, w.astype(np.float32), int((w > 0).sum())


def paths_ref(terms: Sequence) -> np.ndarray:
    """g = sum of c X over terms ((c, X [H, W, 2]), one or two), in float32 as the kernels form it."""
    g = np.float32(terms[0][0]) * np.asarray(terms[0][1], np.float32)
    for c, x in terms[1:]:
        g = g + np.float32(c) * np.asarray(x, np.float32)
    return g.astype(np.float32)
