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
    from skimage.metrics import structural_similarity
    return float(structural_similarity(np.asarray(pred, np.float64), np.asarray(gt, np.float64),
                                       data_range=1.0, channel_axis=-1))
