#!/usr/bin/env python
"""The baselines a 4D model must beat, on a scene's test frames, without any model: the mean of
the two neighbouring training frames, a DIS optical-flow interpolation between them with
bilinear and with bicubic warps, and the in-between teacher (the target training's in-between steps
fit at that time, built from the training frames alone; endowave_cl/baselines.py), scored exactly as `endowave-cl eval` scores a model (PSNR in both
forms, SSIM, LPIPS-Alex when its weights are installed).  On a scene with gt_flow/ it also prints
DIS's end-point error from each test frame to the next (the reference `eval` puts beside the
model's rendered flow).

    python tools/eval_baselines.py ../shared/data/endonerf/pulling_soft_tissues --downscale 2
    python tools/eval_baselines.py SCENE --per-frame --json out.json
    python tools/eval_baselines.py SCENE --validation     # the validation frames, never a test frame
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", help="scene folder in the EndoNeRF layout")
    ap.add_argument("--downscale", type=float, default=1.0, help="image downscale factor (default 1)")
    ap.add_argument("--no-lpips", action="store_true", help="skip LPIPS")
    ap.add_argument("--validation", action="store_true",
                    help="score the validation frames ((i - 5) %% 8 == 0, held out of the training frames) "
                         "instead of the test frames")
    ap.add_argument("--per-frame", action="store_true", help="also print each test frame's figures")
    ap.add_argument("--json", help="write the figures to this file as JSON (atomically)")
    args = ap.parse_args(argv)

    import cv2

    from endowave_cl.atomic import write_bytes_atomic
    from endowave_cl.baselines import LABELS, NAMES, baseline_scores, summarise
    from endowave_cl.data.scene import apply_split, load_scene
    from endowave_cl.device import cpu_name
    from endowave_cl.errors import EndowaveError
    from endowave_cl.evaluation import flow_references
    from endowave_cl.lpips import lpips_available

    try:
        scene = apply_split(load_scene(args.scene, downscale=args.downscale),
                            "validation" if args.validation else "test")
        if not scene.test_indices:
            raise EndowaveError(f"{args.scene}: the scene has no test frame")
        use_lpips = not args.no_lpips and lpips_available()
        t0 = time.perf_counter()
        rows = baseline_scores(scene, use_lpips)
        refs = flow_references(scene)
        seconds = time.perf_counter() - t0
    except EndowaveError as e:
        print(f"eval_baselines: error: {e}", file=sys.stderr)
        return 1

    print(f"host: {cpu_name()}, {os.cpu_count()} CPUs, OpenCV {cv2.__version__}, Python {platform.python_version()}")
    print(f"scene: {args.scene}, {scene.summary()}")
    lp_note = "" if use_lpips else " (n/a: --no-lpips or weights not installed)"
    print(f"{len(rows)} {scene.split} frames; PSNR = whole image of masked images, masked = tissue pixels only; "
          f"LPIPS-Alex{lp_note}; {seconds:.1f} s")
    lp = lambda v: "n/a" if v is None else f"{v:.4f}"
    lw = max(len(LABELS[n]) for n in NAMES)
    print(f"{'baseline':<{lw}} {'PSNR':>7} {'masked':>7} {'SSIM':>7} {'LPIPS':>7}")
    summary = {}
    for name in NAMES:
        s = summarise(rows, name)
        summary[name] = s
        print(f"{LABELS[name]:<{lw}} {s['psnr']:7.2f} {s['psnr_masked']:7.2f} {s['ssim']:7.4f} {lp(s['lpips']):>7}")
    if args.per_frame:
        print(f"{'frame':>6} {'neighbours':>11} {'a':>5} " + " ".join(f"{n + ' PSNR':>14}" for n in NAMES))
        for r in rows:
            print(f"{r['index']:>6} {str(tuple(r['neighbours'])):>11} {r['fraction']:5.2f} "
                  + " ".join(f"{r[n]['psnr']:14.2f}" for n in NAMES))
    dis_flow = None
    if refs:
        import numpy as np
        dis_flow = {"frames": len(refs), "dis_epe": float(np.mean([v[2] for v in refs.values()])),
                    "gt_magnitude": float(np.mean([np.linalg.norm(v[0], axis=-1)[v[1]].mean()
                                                   for v in refs.values()]))}
        print(f"gt_flow: DIS from each test frame to the next, end-point error {dis_flow['dis_epe']:.3f} px "
              f"({dis_flow['frames']} frames; zero flow {dis_flow['gt_magnitude']:.3f} px)")
    if args.json:
        out = {"scene": str(args.scene), "size": [scene.width, scene.height], "downscale": args.downscale,
               "baselines": summary, "per_frame": rows, "flow": dis_flow,
               "host": cpu_name(), "cpus": os.cpu_count(), "opencv": cv2.__version__}
        write_bytes_atomic(args.json, json.dumps(out, indent=1).encode())
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
