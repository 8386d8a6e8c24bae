"""Does a trained model thin out between its training frames?  Prints, for a run, the Gaussians'
temporal std (in frame spacings) and opacity percentiles, then per training frame and at fractions
of the way to the next frame: Gaussians alive (marginal > 0.05), the summed opacity x marginal, the
rendered alpha (mean and 1st percentile) and, at frame times, the PSNR.

    python research/between_coverage.py RUN [--frames 10] [--fractions 0 0.25 0.5]
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run")
    ap.add_argument("--frames", type=int, default=10, help="training frames to look at (first ones)")
    ap.add_argument("--fractions", type=float, nargs="+", default=[0.0, 0.25, 0.5])
    a = ap.parse_args(argv)
    from endowave_cl.errors import EndowaveError
    from endowave_cl.gaussians import covariance_4d, upload
    from endowave_cl.metrics import psnr
    from endowave_cl.render import render
    from endowave_cl.run_io import load_run
    from endowave_cl.runtime import get_runtime
    from endowave_cl.train.motion import motion_of
    try:
        run = load_run(a.run)
    except EndowaveError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    sc, g = run.scene, run.gaussians
    rt = get_runtime()
    params = upload(rt, g)
    times = np.array([sc.frames[k].time for k in sc.train_indices])
    spacing = float(np.median(np.diff(np.unique(times))))
    _, st, _ = motion_of(covariance_4d(g))
    op = 1.0 / (1.0 + np.exp(-g.opacity.astype(np.float64)))
    print(f"{a.run}: step {run.step}, {len(g)} Gaussians, frame spacing {spacing:.5f}; load "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print("temporal std / spacing, percentiles 5 25 50 75 95:", np.round(np.percentile(st / spacing, [5, 25, 50, 75, 95]), 2))
    print("opacity, percentiles 5 25 50 75 95:", np.round(np.percentile(op, [5, 25, 50, 75, 95]), 3))
    train = list(sc.train_indices)
    print(f"{'time':>16} {'alive':>7} {'sum op*m':>9} {'alpha':>7} {'alpha p1':>8} {'PSNR':>6}")
    for i, k in enumerate(train[:a.frames]):
        nxt = train[i + 1] if i + 1 < len(train) else k
        for s in a.fractions:
            t = (1 - s) * sc.frames[k].time + s * sc.frames[nxt].time
            m = np.exp(-0.5 * (t - g.means[:, 3]) ** 2 / st ** 2)
            out = render(rt, params, sc.frames[k].camera, t).host()
            p = f"{psnr(out['image'], sc.frames[k].image):6.2f}" if s == 0 else "      "
            print(f"frame {k:3d} + {s:4.2f} {int((m > 0.05).sum()):7d} {float((m * op).sum()):9.0f} "
                  f"{out['alpha'].mean():7.4f} {np.percentile(out['alpha'], 1):8.4f} {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
