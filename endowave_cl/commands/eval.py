"""Evaluate a trained run on its test frames: PSNR (masked form and whole-image form on masked
images), SSIM, LPIPS-Alex (with the [metrics] extra; else n/a) and rendering FPS (render alone,
after warm-up). Prints the figures and writes RUN/eval.json."""
from __future__ import annotations

import json
import os
from pathlib import Path


def add_arguments(p) -> None:
    p.add_argument("run", help="run folder written by endowave-cl train")
    p.add_argument("--scene", help="scene folder (default: the one the run was trained on)")
    p.add_argument("--fps-runs", type=int, default=10, help="timed renders for the FPS figure")


def run(args) -> int:
    from ..evaluation import evaluate_run
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
