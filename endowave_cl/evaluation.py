"""Evaluation of a model on a scene's test frames, the way papers report it (DESIGN.md)."""
from __future__ import annotations

import statistics
import time

import numpy as np


def evaluate_run(rt, params, scene, fps_runs: int = 10, with_lpips: bool = True) -> dict:
    """Test-frame metrics of device parameters: PSNR (masked form and whole-image form on masked
    images), SSIM, LPIPS-Alex (None when unavailable or not asked for) and render FPS (median of
    fps_runs renders after warm-up; None when fps_runs is 0)."""
    from .lpips import lpips as lpips_distance
    from .lpips import lpips_available
    from .metrics import psnr, psnr_masked, ssim
    from .render import render
    use_lpips = with_lpips and lpips_available()
    ps, pm, ss, lp = [], [], [], []
    for k in scene.test_indices:
        f = scene.frames[k]
        pred = np.clip(render(rt, params, f.camera, f.time).host()["image"], 0, 1)
        mask = np.ones(pred.shape[:2], np.float32) if f.mask is None else f.mask
        pm.append(psnr_masked(pred, f.image, mask))
        pmask, gmask = pred * mask[..., None], f.image * mask[..., None]
        ps.append(psnr(pmask, gmask))
        ss.append(ssim(pmask, gmask))
        if use_lpips:
            lp.append(lpips_distance(pmask, gmask))
    fps = None
    if fps_runs > 0:
        fps = _render_fps(rt, params, scene.frames[scene.test_indices[0]], fps_runs)
    return {"psnr": float(np.mean(ps)), "psnr_masked": float(np.mean(pm)), "ssim": float(np.mean(ss)),
            "lpips": float(np.mean(lp)) if use_lpips else None, "fps": fps,
            "test_frames": len(scene.test_indices), "device": rt.name}


def _render_fps(rt, params, f, runs: int) -> float:
    from .render import render
    for _ in range(3):
        render(rt, params, f.camera, f.time)
    rt.queue.finish()
    ts = []
    for _ in range(runs):
        t0 = time.perf_counter()
        render(rt, params, f.camera, f.time)
        rt.queue.finish()
        ts.append(time.perf_counter() - t0)
    return 1.0 / statistics.median(ts)
