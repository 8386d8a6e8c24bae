#!/usr/bin/env python
"""Straight against curved paths in a flow interpolation of the held-out frames (research/QUALITY.md
finding 31).

    python research/interp_paths.py SCENE [--downscale 2] [--method dis]

For every test frame k with training neighbours i0 < k < i1 and a training frame beyond each of
them (b before i0, a after i1; the same camera), the frame at k is predicted from i0 and i1 by
the DIS baseline's construction (each frame sampled bicubically along its own flow, the two
blended by the time fraction) with two kinds of path:

- straight: frame i0's pixels move the fraction s of their flow to i1 (the DIS baseline itself,
  bicubic warps);
- curved: along the parabola through their positions at i0, i1 and b (train/between.py
  path_displacement, what between_path = "quadratic" does in the in-between target); frame i1's
  likewise through i1, i0 and a.

Prints the PSNR (dB) of both and of the neighbour mean per test frame and their means, and the
mean displacement and mean bend (the curved path's departure from the straight one) at k.  Four
frames carry more than two only where the motion changes speed within the pair's neighbourhood.
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--method", default="dis", help="flow estimator (data/flow.py METHODS), default dis")
    a = ap.parse_args(argv)
    from endowave_cl.baselines import mean_interpolation, neighbours, sample_displaced
    from endowave_cl.data.flow import METHODS, estimate_flow
    from endowave_cl.data.scene import load_scene
    from endowave_cl.errors import EndowaveError
    from endowave_cl.metrics import psnr
    from endowave_cl.train.between import frames_beyond, path_displacement
    if a.method not in METHODS:
        ap.error(f"--method must be one of {', '.join(METHODS)}")
    try:
        sc = load_scene(a.scene, downscale=a.downscale)
    except EndowaveError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"{a.scene} {sc.width}x{sc.height}, {len(sc.frames)} frames, flow {a.method}; load "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(f"{'frame':>5} {'mean':>7} {'straight':>9} {'curved':>7} {'|d| px':>7} {'bend px':>8}")
    rows = []
    for k in sc.test_indices:
        i0, i1, s = neighbours(sc, k)
        if i0 == i1:
            continue
        b, after = frames_beyond(sc, i0, i1)
        if b is None or after is None:
            continue
        im = {i: sc.frames[i].image for i in (b, i0, i1, after)}
        t = {i: float(sc.frames[i].time) for i in (b, i0, i1, after)}
        flow = {(i, j): estimate_flow(im[i], im[j], a.method) for i, j in ((i0, i1), (i1, i0), (i0, b), (i1, after))}
        span = t[i1] - t[i0]
        straight = (s * flow[(i0, i1)], (1.0 - s) * flow[(i1, i0)])                  # [H, W, 2] each
        curved = (path_displacement(flow[(i0, i1)], s, span, flow[(i0, b)], t[b] - t[i0]),
                  path_displacement(flow[(i1, i0)], 1.0 - s, -span, flow[(i1, after)], t[after] - t[i1]))
        pred = {name: mean_interpolation(sample_displaced(im[i0], -g0, "cubic"), sample_displaced(im[i1], -g1, "cubic"), s)
                for name, (g0, g1) in (("straight", straight), ("curved", curved))}
        gt = sc.frames[k].image
        row = [psnr(mean_interpolation(im[i0], im[i1], s), gt), psnr(pred["straight"], gt), psnr(pred["curved"], gt),
               float(np.linalg.norm(straight[0], axis=-1).mean()),
               float(np.linalg.norm(curved[0] - straight[0], axis=-1).mean())]
        rows.append(row)
        print(f"{k:>5} {row[0]:>7.2f} {row[1]:>9.2f} {row[2]:>7.2f} {row[3]:>7.2f} {row[4]:>8.2f}")
    if not rows:
        print("no test frame has two training frames on each side")
        return 0
    m = np.mean(rows, axis=0)
    print(f"{'mean':>5} {m[0]:>7.2f} {m[1]:>9.2f} {m[2]:>7.2f} {m[3]:>7.2f} {m[4]:>8.2f}   ({len(rows)} test frames)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
