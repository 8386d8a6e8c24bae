#!/usr/bin/env python
"""Quality run and loss ablation, as in the paper's ablation table.

Trains the full method and the same run with one loss removed (flow, wavelet, depth) on one scene
at a chosen resolution and step budget, evaluates each on the test frames (PSNR both forms, SSIM,
LPIPS when the [metrics] extra is installed, render FPS) and prints a table; writes the table as
JSON and Markdown next to the runs.

    python tools/ablation.py --scene ../shared/data/endonerf/pulling_soft_tissues --downscale 2 \
        --iterations 3000 --out runs/ablation [--variants full,no_flow,no_wavelet,no_depth]
    python tools/ablation.py --synthetic --iterations 2000 --out runs/ablation_synth   # has depth
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

VARIANTS = {"full": {}, "no_flow": {"use_flow": False}, "no_wavelet": {"use_wavelet": False},
            "no_depth": {"use_depth": False}}


def depth_error(rt, params, scene) -> float:
    """Mean |rendered depth - ground truth| (scene units) over the test frames' valid tissue pixels;
    the rendered depth is divided by the accumulated alpha (the expected depth of what is seen)."""
    import numpy as np

    from endowave_cl.render import render
    errs = []
    for k in scene.test_indices:
        f = scene.frames[k]
        h = render(rt, params, f.camera, f.time).host()
        pred = h["depth"] / np.maximum(h["alpha"], 1e-6)
        valid = (f.depth > 0) & (np.ones_like(f.depth, bool) if f.mask is None else f.mask > 0.5)
        errs.append(np.abs(pred - f.depth)[valid])
    return float(np.concatenate(errs).mean())


def _previous_rows(out: Path):
    p = out / "ablation.json"
    return json.loads(p.read_text()) if p.is_file() else []


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene")
    ap.add_argument("--synthetic", action="store_true", help="generate a synthetic scene with depth and masks")
    ap.add_argument("--synthetic-size", default="320x256x32", help="WxHxFRAMES of the synthetic scene")
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--iterations", type=int, default=3000)
    ap.add_argument("--init-points", type=int, default=30000)
    ap.add_argument("--variants", default="full,no_flow,no_wavelet,no_depth")
    ap.add_argument("--out", required=True)
    ap.add_argument("--device", default=None)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--evaluate-only", action="store_true",
                    help="do not train: evaluate the newest checkpoint of each variant's run folder")
    args = ap.parse_args(argv)

    from endowave_cl.evaluation import evaluate_run
    from endowave_cl.data.scene import load_scene
    from endowave_cl.runtime import get_runtime
    from endowave_cl.train.config import load_config
    from endowave_cl.train.trainer import Trainer

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.synthetic:
        from endowave_cl.data.synth import make_synthetic_scene
        w, h, n = (int(v) for v in args.synthetic_size.split("x"))
        scene_path = out / "synthetic_scene"
        if not (scene_path / "poses_bounds.npy").is_file():
            make_synthetic_scene(scene_path, width=w, height=h, frames=n, seed=0, force=True)
    else:
        scene_path = Path(args.scene)
    rt = get_runtime(args.device)
    overrides = dict(s.split("=", 1) for s in args.set)
    rows = []
    for name in args.variants.split(","):
        cfg = load_config(None, overrides)
        cfg.iterations, cfg.downscale, cfg.init_points = args.iterations, args.downscale, args.init_points
        for k, v in VARIANTS[name].items():
            setattr(cfg, k, v)
        scene = load_scene(scene_path, downscale=cfg.downscale, use_depth=cfg.use_depth)
        if not scene.has_depth:
            cfg.use_depth = False
        print(f"== {name}: {scene.summary()}", flush=True)
        if args.evaluate_only:
            from endowave_cl.gaussians import upload
            from endowave_cl.checkpoint import latest_checkpoint, load_checkpoint
            ck = latest_checkpoint(out / name)
            params = upload(rt, load_checkpoint(ck)["gaussians"])
            old = [r for r in _previous_rows(out) if r["variant"] == name]
            secs = old[0]["seconds"] if old else float("nan")
        else:
            t0 = time.perf_counter()
            tr = Trainer(scene, cfg, out / name, rt, resume=False)
            tr.train(progress=False)
            secs = time.perf_counter() - t0
            params = tr.params
        eval_scene = load_scene(scene_path, downscale=cfg.downscale)   # with depth, whatever was trained
        m = evaluate_run(rt, params, eval_scene)
        m["depth_mae"] = depth_error(rt, params, eval_scene) if eval_scene.has_depth else None
        m.update({"variant": name, "seconds": secs, "gaussians": len(params["means"]),
                  "use_depth": cfg.use_depth, "use_flow": cfg.use_flow, "use_wavelet": cfg.use_wavelet})
        rows.append(m)
        print(json.dumps(m), flush=True)
    lines = [f"scene {scene_path}, {scene.width}x{scene.height}, {args.iterations} steps, device {rt.name}", "",
             "| variant | depth | flow | wavelet | PSNR | PSNR (masked) | SSIM | LPIPS | depth MAE | FPS | train s | Gaussians |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for m in rows:
        lp = "n/a" if m["lpips"] is None else f"{m['lpips']:.4f}"
        dm = "n/a" if m["depth_mae"] is None else f"{m['depth_mae']:.4f}"
        lines.append(f"| {m['variant']} | {'y' if m['use_depth'] else '-'} | {'y' if m['use_flow'] else '-'} | "
                     f"{'y' if m['use_wavelet'] else '-'} | {m['psnr']:.2f} | {m['psnr_masked']:.2f} | "
                     f"{m['ssim']:.4f} | {lp} | {dm} | {m['fps']:.1f} | {m['seconds']:.0f} | {m['gaussians']} |")
    table = "\n".join(lines)
    print(table)
    (out / "ablation.md").write_text(table + "\n")
    (out / "ablation.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
