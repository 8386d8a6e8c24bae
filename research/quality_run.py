"""Train a scene with given settings and seeds; print test-frame quality beside the baselines.

    python research/quality_run.py SCENE --downscale 2 --seeds 0 1 2 [--minutes 15] [--set KEY=VALUE ...]

Per seed: test PSNR (whole image of masked images, and masked pixels only), SSIM, LPIPS-Alex, the
neighbour-mean and DIS-flow-interpolation baselines on the same test frames (evaluation.py), the
margin over the better baseline, training-frame PSNR (every third training frame), the rendered
flow's end-point error where the scene has gt_flow/, Gaussians, steps and training seconds; then the
mean and spread over the seeds, the machine and its load.  --json writes everything to a file.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from endowave_cl.device import cpu_name
from endowave_cl.errors import EndowaveError


def _machine() -> str:
    return f"{cpu_name()}, {os.cpu_count()} cores, load {' '.join(f'{x:.2f}' for x in os.getloadavg())}"


def train_frame_psnr(rt, params, scene, every: int = 3) -> float:
    from endowave_cl.metrics import frame_scores
    from endowave_cl.render import render
    vals = []
    for k in list(scene.train_indices)[::every]:
        f = scene.frames[k]
        vals.append(frame_scores(render(rt, params, f.camera, f.time).host()["image"], f.image, f.mask, False)["psnr"])
    return float(np.mean(vals))


def run_one(scene_path, downscale, seed, overrides, minutes, out_root):
    from endowave_cl.data.scene import load_scene
    from endowave_cl.evaluation import evaluate_run
    from endowave_cl.runtime import get_runtime
    from endowave_cl.train.config import load_config
    from endowave_cl.train.trainer import Trainer
    cfg = load_config(None, {**overrides, "seed": str(seed), "downscale": str(downscale)})
    if minutes:
        cfg = cfg.replace(minutes=minutes)
    scene = load_scene(scene_path, downscale=cfg.downscale, use_depth=cfg.use_depth)
    if not scene.has_depth:
        cfg = cfg.replace(use_depth=False)
    rt = get_runtime()
    tr = Trainer(scene, cfg, Path(out_root) / f"seed{seed}", rt, log=lambda s: None, resume=False)
    fin = tr.train(progress=False)
    m = evaluate_run(rt, tr.params, scene, fps_runs=0, with_lpips=True, with_baselines=True)
    per_frame = m.pop("per_frame", None) or []
    m["per_frame_psnr"] = {int(r["index"]): round(float(r["model"]["psnr"]), 3) for r in per_frame}
    m.update(train_psnr=train_frame_psnr(rt, tr.params, scene), steps=fin["step"], gaussians=fin["gaussians"],
             train_seconds=fin["train_seconds"], seed=seed, history=[(h["step"], h.get("psnr")) for h in tr.history])
    return m


def _fmt(v, nd=2):
    return "n/a" if v is None else f"{v:.{nd}f}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--minutes", type=float, default=0.0, help="time budget per seed (0: the config's steps)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--out", help="folder for the runs (default: a temporary folder)")
    ap.add_argument("--json", help="write all figures to this file")
    a = ap.parse_args(argv)
    overrides = dict(s.split("=", 1) for s in a.set)
    out_root = a.out or tempfile.mkdtemp(prefix="quality-")
    print(f"machine: {_machine()}")
    print(f"scene {a.scene}, downscale {a.downscale}, settings {overrides or 'defaults'}"
          + (f", {a.minutes:g} min budget" if a.minutes else ""))
    rows = []
    try:
        _run_seeds(a, overrides, out_root, rows)
    except (KeyboardInterrupt, EndowaveError) as e:   # Ctrl-C, SIGTERM (a saved checkpoint) or bad input
        print(f"quality_run: {'error: ' if isinstance(e, EndowaveError) else ''}{e or 'interrupted'}"
              + (f"; the {len(rows)} finished seed(s) are in {a.json}" if a.json and rows else ""), file=sys.stderr)
        _write_json(a, overrides, rows)
        return 1 if isinstance(e, EndowaveError) else 130
    _write_json(a, overrides, rows)
    return 0


def _write_json(a, overrides, rows):
    if a.json and rows:
        from endowave_cl.atomic import write_json_atomic
        write_json_atomic(a.json, {"machine": _machine(), "scene": a.scene, "downscale": a.downscale,
                                   "settings": overrides, "minutes": a.minutes, "runs": rows})


def _run_seeds(a, overrides, out_root, rows):
    for seed in a.seeds:
        t0 = time.perf_counter()
        m = run_one(a.scene, a.downscale, seed, overrides, a.minutes, out_root)
        rows.append(m)
        b = m.get("baselines") or {}
        fl = m.get("flow")
        print(f"seed {seed}: test PSNR {_fmt(m['psnr'])} (masked {_fmt(m['psnr_masked'])}), SSIM {_fmt(m['ssim'], 4)}, "
              f"LPIPS {_fmt(m['lpips'], 4)}; train-frame PSNR {_fmt(m['train_psnr'])}; "
              + ", ".join(f"{n} {_fmt(v['psnr'])}" for n, v in b.items())
              + f"; margin {_fmt(m.get('margin', {}).get('psnr'))}"
              + (f"; flow EPE {_fmt(fl['model_epe'], 3)} px (DIS {_fmt(fl['dis_epe'], 3)})" if fl else "")
              + (f"; depth MAE {m['depth']['mae']:.4g} ({100 * m['depth']['relative']:.2f}%)" if m.get("depth") else "")
              + f"; {m['gaussians']} Gaussians, {m['steps']} steps, {m['train_seconds']:.0f} s training "
              f"({time.perf_counter() - t0:.0f} s in all); load now {os.getloadavg()[0]:.2f}")
        sys.stdout.flush()
    if len(rows) > 1:
        def ms(key, sub=None):
            v = [(r[key] if sub is None else (r.get(key) or {}).get(sub)) for r in rows]
            v = [x for x in v if x is not None]
            return (statistics.mean(v), statistics.stdev(v)) if len(v) > 1 else (None, None)
        parts = []
        for label, key, sub in (("test PSNR", "psnr", None), ("masked", "psnr_masked", None), ("SSIM", "ssim", None),
                                ("LPIPS", "lpips", None), ("train PSNR", "train_psnr", None),
                                ("margin", "margin", "psnr"), ("flow EPE", "flow", "model_epe"),
                                ("depth MAE", "depth", "mae")):
            mu, sd = ms(key, sub)
            if mu is not None:
                parts.append(f"{label} {mu:.3f} +- {sd:.3f}")
        print(f"mean +- std over seeds {a.seeds}: " + "; ".join(parts))


if __name__ == "__main__":
    sys.exit(main())
