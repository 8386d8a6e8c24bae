"""The flow-interpolation baseline with other OpenCV flow estimators, alone and fused: does a better
pseudo ground truth, or a better in-between target, exist here?

For every frame k of the sequence that has frames on both sides, the frame is interpolated from
frames k - 1 and k + 1 (each warped half-way along its flow and the two blended, baselines.py),
with each estimator of data/flow.py METHODS given by --methods, and with the estimators of each
--fuse group fused per pixel by how well their warps agree (train/between.py
fused_interpolation, what `between_flows` gives the in-between target).  Printed per
interpolator: PSNR over all those frames, PSNR and LPIPS over the scene's test frames (whose
neighbours k - 1, k + 1 are what the model's in-between steps see there), and the time the
estimator took per flow.

    python research/interp_flows.py SCENE --downscale 2
    python research/interp_flows.py SCENE --methods dis dis_fine farneback deepflow --fuse dis,farneback dis,dis_fine,farneback
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--methods", nargs="+", default=["dis", "dis_fine", "farneback"],
                    help="estimators (data/flow.py METHODS), each scored alone")
    ap.add_argument("--fuse", nargs="*", default=["dis,dis_fine,farneback"],
                    help="comma-separated groups of --methods to fuse (default: the three)")
    ap.add_argument("--sampler", default="cubic", help="how the warps sample the frames (baselines.SAMPLERS)")
    a = ap.parse_args(argv)
    from endowave_cl.baselines import SAMPLERS, sample_displaced
    from endowave_cl.data.flow import METHODS, estimate_flow
    from endowave_cl.data.scene import load_scene
    from endowave_cl.errors import EndowaveError
    from endowave_cl.lpips import lpips, lpips_available
    from endowave_cl.metrics import psnr
    from endowave_cl.train.between import fused_interpolation
    groups = [tuple(g.split(",")) for g in a.fuse]
    bad = [m for m in a.methods if m not in METHODS] + [m for g in groups for m in g if m not in a.methods]
    if bad or a.sampler not in SAMPLERS:
        ap.error(f"unknown or unlisted method(s) {bad}; --methods from {', '.join(METHODS)}, --fuse from "
                 f"--methods" if bad else f"--sampler must be one of {', '.join(SAMPLERS)}")
    try:
        sc = load_scene(a.scene, downscale=a.downscale)
    except EndowaveError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    n, test = len(sc.frames), set(sc.test_indices)
    print(f"{a.scene} {sc.width}x{sc.height}, frames 1..{n - 2} from their two neighbours, test frames "
          f"{sorted(test)}; {a.sampler} warps; load {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    scores, lp, secs = {}, {}, {m: [] for m in a.methods}
    for k in range(1, n - 1):
        im0, im1, gt = sc.frames[k - 1].image, sc.frames[k + 1].image, sc.frames[k].image
        warps = {}
        for m in a.methods:
            t0 = time.perf_counter()
            f01, f10 = estimate_flow(im0, im1, m), estimate_flow(im1, im0, m)
            secs[m].append((time.perf_counter() - t0) / 2)
            warps[m] = (sample_displaced(im0, -0.5 * f01, a.sampler), sample_displaced(im1, -0.5 * f10, a.sampler))
        images = {m: 0.5 * (w0 + w1) for m, (w0, w1) in warps.items()}
        for g in groups:
            images["fused " + "+".join(g)] = fused_interpolation([warps[m] for m in g], 0.5)[0]
        for name, img in images.items():
            scores.setdefault(name, []).append((k, psnr(img, gt)))
            if k in test and lpips_available():
                lp.setdefault(name, []).append(lpips(img, gt))
    print(f"| interpolator | PSNR, all {n - 2} frames | PSNR, test frames | LPIPS, test frames | s per flow |")
    print("|---|---|---|---|---|")
    for name, v in scores.items():
        on_test = [p for k, p in v if k in test]
        cost = (sum(np.median(secs[m]) for m in name[6:].split("+")) if name.startswith("fused ")
                else np.median(secs[name]))
        print(f"| {name} | {np.mean([p for _, p in v]):.2f} | {np.mean(on_test) if on_test else float('nan'):.2f} | "
              f"{np.mean(lp[name]) if name in lp else float('nan'):.4f} | {cost:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
