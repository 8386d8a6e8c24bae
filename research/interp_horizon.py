#!/usr/bin/env python
"""How far in time the frames of a video predict each other: the interpolation baselines from the
frames d steps before and after a frame, for d = 1, 2, 3 ...

A 4D model renders an unseen time from what its training frames show; if a frame is predicted well
only by its immediate neighbours, the model cannot do much better than a two-frame interpolation
there, however many frames it fits.  Per gap d, over every frame k with k - d and k + d in the
sequence (all frames, training or test: this measures the video, not a model), and over the test
frames alone, the PSNR of:

- ``mean``: the mean of frames k - d and k + d;
- ``dis``: OpenCV DIS flow both ways between them, each warped half-way and averaged (the DIS
  baseline's construction, baselines.py);
- ``dis two-flow``: the same with the intermediate flow taken from both flows, as Super SloMo
  approximates it (baselines.two_flow_displacements).

    python research/interp_horizon.py ../shared/data/endonerf/pulling_soft_tissues --downscale 2 --gaps 1 2 3
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np


def interpolations(im0: np.ndarray, im1: np.ndarray, t: float = 0.5):
    """{"mean", "dis", "dis two-flow"}: images [H, W, 3] at fraction t between im0 and im1."""
    from endowave_cl.baselines import mean_interpolation, sample_displaced, two_flow_displacements, warp_backward
    from endowave_cl.data.flow import estimate_flow
    f01, f10 = estimate_flow(im0, im1, "dis"), estimate_flow(im1, im0, "dis")     # [H, W, 2] each
    d0, d1 = two_flow_displacements(f01, f10, t)
    return {"mean": mean_interpolation(im0, im1, t),
            "dis": mean_interpolation(warp_backward(im0, f01, t), warp_backward(im1, f10, 1.0 - t), t),
            "dis two-flow": mean_interpolation(sample_displaced(im0, d0), sample_displaced(im1, d1), t)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--gaps", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--per-frame", action="store_true",
                    help="also print the DIS interpolation's PSNR per test frame and gap, and that of the "
                         "gap-1 and gap-2 interpolations blended 2:1")
    a = ap.parse_args(argv)
    from endowave_cl.data.scene import load_scene
    from endowave_cl.errors import EndowaveError
    from endowave_cl.metrics import psnr
    if min(a.gaps) < 1:
        ap.error("--gaps must be >= 1")
    try:
        sc = load_scene(a.scene, downscale=a.downscale)
    except EndowaveError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    n = len(sc.frames)
    test = set(sc.test_indices)
    print(f"{a.scene} {sc.width}x{sc.height}, {n} frames; load {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    per_frame = {}      # (k, d) -> {name: image} for the test frames, with --per-frame
    print("| gap d | frames | mean (all) | dis (all) | dis two-flow (all) | mean (test) | dis (test) | dis two-flow (test) |")
    print("|---|---|---|---|---|---|---|---|")
    for d in a.gaps:
        scores = {}     # name -> [(k, psnr)]
        for k in range(d, n - d):
            images = interpolations(sc.frames[k - d].image, sc.frames[k + d].image)
            for name, img in images.items():
                scores.setdefault(name, []).append((k, psnr(img, sc.frames[k].image)))
            if a.per_frame and k in test:
                per_frame[(k, d)] = images
        if not scores:
            print(f"| {d} | 0 | | | | | | |")
            continue
        names = ("mean", "dis", "dis two-flow")
        every = [np.mean([p for _, p in scores[m]]) for m in names]
        on_test = [[p for k, p in scores[m] if k in test] for m in names]
        cells = [f"{x:.2f}" for x in every] + [f"{np.mean(x):.2f}" if x else "" for x in on_test]
        print(f"| {d} | {len(scores['dis'])} | " + " | ".join(cells) + " |")
    if a.per_frame:
        print("\nDIS interpolation per test frame (dB):")
        for k in sorted(test):
            row = [f"d={d}: {psnr(per_frame[(k, d)]['dis'], sc.frames[k].image):.2f}"
                   for d in a.gaps if (k, d) in per_frame]
            if (k, 1) in per_frame and (k, 2) in per_frame:
                blend = (2.0 * per_frame[(k, 1)]["dis"] + per_frame[(k, 2)]["dis"]) / 3.0
                row.append(f"gaps 1 and 2 blended 2:1: {psnr(blend, sc.frames[k].image):.2f}")
            print(f"  frame {k}: " + ", ".join(row))
    return 0


if __name__ == "__main__":
    sys.exit(main())
