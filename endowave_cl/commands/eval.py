"""Evaluate a trained run on its test frames: PSNR (masked form and whole-image form on masked
images), SSIM, LPIPS-Alex (with the [metrics] extra; else n/a) and rendering FPS (render alone,
after warm-up). Prints the figures and writes RUN/eval.json."""
from __future__ import annotations

import json
import os
import statistics
import time
from pathlib import Path

import numpy as np


def add_arguments(p) -> None:
    p.add_argument("run", help="run folder written by endowave-cl train")
    p.add_argument("--scene", help="scene folder (default: the one the run was trained on)")
    p.add_argument("--fps-runs", type=int, default=10, help="timed renders for the FPS figure")


def evaluate_run(rt, params, scene, fps_runs: int = 10) -> dict:
    from ..metrics import psnr, psnr_masked, ssim
    from ..render import render
    from ..lpips import lpips as lpips_distance
    from ..lpips import lpips_available
    use_lpips = lpips_available()
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
    f = scene.frames[scene.test_indices[0]]
    for _ in range(3):
        render(rt, params, f.camera, f.time)
    rt.queue.finish()
    ts = []
    for _ in range(fps_runs):
        t0 = time.perf_counter()
        render(rt, params, f.camera, f.time)
        rt.queue.finish()
        ts.append(time.perf_counter() - t0)
    return {"psnr": float(np.mean(ps)), "psnr_masked": float(np.mean(pm)), "ssim": float(np.mean(ss)),
            "lpips": float(np.mean(lp)) if use_lpips else None, "fps": 1.0 / statistics.median(ts),
            "test_frames": len(scene.test_indices), "device": rt.name}


def run(args) -> int:
    from ..gaussians import upload
    from ..run_io import load_run
    from ..runtime import get_runtime
    r = load_run(args.run, args.scene)
    rt = get_runtime(getattr(args, "device", None))
    m = evaluate_run(rt, upload(rt, r.gaussians), r.scene, args.fps_runs)
    m.update({"step": r.step, "gaussians": len(r.gaussians), "checkpoint": str(r.checkpoint)})
    lp = "n/a (install the [metrics] extra)" if m["lpips"] is None else f"{m['lpips']:.4f}"
    print(f"{m['test_frames']} test frames, step {r.step}, {m['gaussians']} Gaussians")
    print(f"PSNR {m['psnr']:.2f} dB (masked form {m['psnr_masked']:.2f} dB)  SSIM {m['ssim']:.4f}  "
          f"LPIPS {lp}  FPS {m['fps']:.1f} on {rt.name}")
    path = Path(args.run) / "eval.json"
    tmp = path.with_name(f"eval.json.tmp{os.getpid()}")
    tmp.write_text(json.dumps(m, indent=1))
    os.replace(tmp, path)
    print(f"wrote {path}")
    return 0
