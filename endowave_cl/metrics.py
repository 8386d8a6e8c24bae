"""Image quality metrics as papers report them (DESIGN.md "Evaluation").

Images are [H, W, 3] float arrays in [0, 1]; mask [H, W] with 1 = tissue.
- psnr_masked: the masked form, MSE = sum(sq * mask) / (3 * mask.sum());
- psnr: whole-image MSE (most papers print this on masked images: callers pass pred * mask, gt * mask);
- ssim: scikit-image structural_similarity, data_range 1, channel_axis -1 (its default 7 x 7 window);
- LPIPS-Alex: endowave_cl.lpips (lpips_available() says whether its weights are installed).
"""
from __future__ import annotations

import math

import numpy as np

from .lpips import lpips


def _psnr_from_mse(mse: float) -> float:
    return float("inf") if mse <= 0 else 10.0 * math.log10(1.0 / mse)


def psnr_masked(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    sq = (np.asarray(pred, np.float64) - np.asarray(gt, np.float64)) ** 2   # [H, W, 3]
    m = np.asarray(mask, np.float64)                                        # [H, W]
    denom = 3.0 * m.sum()
    if denom <= 0:
        raise ValueError("psnr_masked: the mask selects no pixel")
    return _psnr_from_mse(float((sq * m[..., None]).sum() / denom))


def psnr(pred: np.ndarray, gt: np.ndarray) -> float:
    return _psnr_from_mse(float(np.mean((np.asarray(pred, np.float64) - np.asarray(gt, np.float64)) ** 2)))


def ssim(pred: np.ndarray, gt: np.ndarray) -> float:
    from skimage.metrics import structural_similarity   # on first use: it imports scipy (~0.3 s)
    return float(structural_similarity(np.asarray(pred, np.float64), np.asarray(gt, np.float64),
                                       data_range=1.0, channel_axis=-1))


def frame_scores(pred: np.ndarray, gt: np.ndarray, mask=None, with_lpips: bool = False) -> dict:
    """Every test-frame figure of one prediction, the way the model and the baselines are scored:
    psnr_masked on the tissue mask, and psnr / ssim / lpips on the masked images (pred * mask,
    gt * mask).  mask None = every pixel; lpips None unless with_lpips (the caller checks that the
    weights are installed)."""
    pred = np.clip(np.asarray(pred, np.float32), 0, 1)
    gt = np.asarray(gt, np.float32)
    if pred.shape != gt.shape or gt.ndim != 3 or gt.shape[2] != 3:
        raise ValueError(f"frame_scores: images must both be [H, W, 3], got {pred.shape} and {gt.shape}")
    m = np.ones(gt.shape[:2], np.float32) if mask is None else np.asarray(mask, np.float32)
    pmask, gmask = pred * m[..., None], gt * m[..., None]
    out = {"psnr": psnr(pmask, gmask), "psnr_masked": psnr_masked(pred, gt, m), "ssim": ssim(pmask, gmask),
           "lpips": None}
    if with_lpips:
        out["lpips"] = lpips(pmask, gmask)
    return out
