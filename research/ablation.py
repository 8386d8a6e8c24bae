#!/usr/bin/env python
"""Loss ablation, as in the paper's ablation table, over several seeds and beside the baselines.

Trains the defaults ("full") and the same run with one loss removed (flow, wavelet, depth), or
without the steps between training frames (no_between: between_prob 0), with the in-between
steps kept at their share until the end instead of fading to half of it after densify_until
(no_between_fade), without
the late learning-rate decay (no_lr_anneal; both schedules start at densify_until: with fewer
--iterations than that, give --set densify_until=N below it), with the in-between target
fused from three flow estimators (fused_between: between_flows = dis_fine,farneback), with the
in-between target's pixels moving on straight paths instead of curved ones (straight_between:
between_path = linear), on one scene, for each seed;
evaluates each on the test frames (PSNR both forms, SSIM, LPIPS-Alex, the neighbour-mean and
DIS-interpolation baselines (bilinear and bicubic warps), the rendered flow's EPE where the scene has gt_flow/,
the depth error where it has depth) and prints one row per variant with the mean and spread over
the seeds.  Writes ablation.json and ablation.md into --out.

    python research/ablation.py --scene ../shared/data/endonerf/pulling_soft_tissues --downscale 2 \
        --iterations 1000 --seeds 0 1 2 --variants full,no_flow,no_wavelet --out runs/ablation
    python research/ablation.py --synthetic --iterations 1000 --seeds 0 1 2 --out runs/ablation_synth
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))   # quality_run

VARIANTS = {"full": {}, "no_flow": {"use_flow": "false"}, "no_wavelet": {"use_wavelet": "false"},
            "no_depth": {"use_depth": "false"}, "no_between": {"between_prob": "0"},
            "plain_adam": {"adam_skip_culled": "false"},
            "no_between_fade": {"between_anneal_final": "1"}, "no_lr_anneal": {"lr_anneal_final": "1"},
            "fused_between": {"between_flows": "dis_fine,farneback"},
            "straight_between": {"between_path": "linear"}}


def depth_error(rt, params, scene) -> float:
    """Mean |rendered depth - depth map| over the test frames' valid tissue pixels, in the units of
    the scene's depth files (evaluation.py's depth figures, without the rest of an evaluation)."""
    from endowave_cl.evaluation import depth_figures
    return depth_figures(rt, params, scene)["mae"]


def _stat(rows, get, nd: int = 3):
    vals = [v for v in (get(r) for r in rows) if v is not None]
    if not vals:
        return "n/a"
    if len(vals) == 1:
        return f"{vals[0]:.{nd}f}"
    return f"{statistics.mean(vals):.{nd}f} +- {statistics.stdev(vals):.{nd}f}"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene")
    ap.add_argument("--synthetic", action="store_true", help="generate a synthetic scene with depth, masks and gt_flow")
    ap.add_argument("--synthetic-size", default="160x128x32", help="WxHxFRAMES of the synthetic scene")
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--iterations", type=int, default=0, help="steps per run (0: the config's default)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--variants", default="full,no_between,no_flow,no_wavelet,no_depth")
    ap.add_argument("--out", required=True)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args(argv)
    unknown = [v for v in args.variants.split(",") if v not in VARIANTS]
    if unknown or not (args.scene or args.synthetic):
        ap.error(f"unknown variant(s) {unknown}; choose from {list(VARIANTS)}" if unknown
                 else "give --scene SCENE or --synthetic")

    from quality_run import _machine, run_one

    from endowave_cl.data.scene import load_scene
    from endowave_cl.gaussians import upload
    from endowave_cl.runtime import get_runtime
    from endowave_cl.checkpoint import latest_checkpoint, load_checkpoint

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
    print(f"machine: {_machine()}", flush=True)
    base = dict(s.split("=", 1) for s in args.set)
    if args.iterations:
        base["iterations"] = str(args.iterations)
    rt = get_runtime()
    eval_scene = load_scene(scene_path, downscale=args.downscale)   # with depth, whatever was trained
    rows = []
    for name in args.variants.split(","):
        for seed in args.seeds:
            run_dir = out / name
            m = run_one(scene_path, args.downscale, seed, {**base, **VARIANTS[name]}, 0.0, run_dir)
            m["depth_mae"] = None
            if eval_scene.has_depth:
                params = upload(rt, load_checkpoint(latest_checkpoint(run_dir / f"seed{seed}"))["gaussians"])
                m["depth_mae"] = depth_error(rt, params, eval_scene)
            m["variant"] = name
            rows.append(m)
            print(json.dumps({k: v for k, v in m.items() if k != "history"}), flush=True)
    b = rows[0].get("baselines") or {}
    lines = [f"scene {scene_path}, {eval_scene.width}x{eval_scene.height}, "
             f"{rows[0]['steps']} steps, seeds {args.seeds}, {_machine()}", "",
             "| variant | PSNR | PSNR (masked) | SSIM | LPIPS | train PSNR | flow EPE px | depth MAE | Gaussians |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name in args.variants.split(","):
        rs = [r for r in rows if r["variant"] == name]
        lines.append(f"| {name} | {_stat(rs, lambda r: r['psnr'])} | {_stat(rs, lambda r: r['psnr_masked'])} | "
                     f"{_stat(rs, lambda r: r['ssim'])} | {_stat(rs, lambda r: r['lpips'])} | "
                     f"{_stat(rs, lambda r: r['train_psnr'])} | "
                     f"{_stat(rs, lambda r: (r.get('flow') or {}).get('model_epe'))} | "
                     f"{_stat(rs, lambda r: r['depth_mae'])} | {_stat(rs, lambda r: float(r['gaussians']), 0)} |")
    for bn, bv in b.items():
        lines.append(f"| baseline: {bn} | {bv['psnr']:.3f} | {bv['psnr_masked']:.3f} | {bv['ssim']:.3f} | "
                     f"{'n/a' if bv.get('lpips') is None else format(bv['lpips'], '.3f')} | | | | |")
    table = "\n".join(lines)
    print(table)
    from endowave_cl.atomic import write_bytes_atomic, write_json_atomic
    write_bytes_atomic(out / "ablation.md", (table + "\n").encode())
    write_json_atomic(out / "ablation.json", rows)


if __name__ == "__main__":
    main()
