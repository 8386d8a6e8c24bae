"""How close a trained model's test frames are to the DIS interpolation that the in-between steps
teach it (research/QUALITY.md, finding 8).

    python research/teacher_gap.py RUN

Per test frame k (neighbours k0, k1 in the training set, fraction s): PSNR against the ground truth
of the model, of the DIS interpolation (the baseline) and of the in-between target that training
saw for that time (train/between.py: the training pair's cached flow, warped and blended, its paths
bent by the neighbouring pairs' flows with between_path "quadratic"; without the model's half), and the
PSNR of the model against each of the two: a model that sits much closer to its teacher than to
the ground truth has learned the teacher's errors too.  The pair (k0, k1) that spans a test frame
is a training pair, so its in-between target at s is exactly what the model was fitted to there.
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", help="a training run folder (config.json and a checkpoint)")
    a = ap.parse_args(argv)
    from endowave_cl.baselines import baseline_images, neighbours
    from endowave_cl.data.flow import flow_for_scene
    from endowave_cl.errors import EndowaveError
    from endowave_cl.gaussians import upload
    from endowave_cl.metrics import psnr
    from endowave_cl.render import render
    from endowave_cl.run_io import load_run
    from endowave_cl.runtime import get_runtime
    from endowave_cl.train.between import between_target, consistent_flows, extra_pairs, pair_bend, usable_pairs
    try:
        run = load_run(a.run)
    except EndowaveError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    sc = run.scene
    rt = get_runtime()
    params = upload(rt, run.gaussians)
    from endowave_cl.train.config import between_flow_methods
    pairs = {p.src: p for p in dict(flow_for_scene(sc, method=run.cfg.flow_method, progress=False,
                                                        max_pixels=run.cfg.flow_max_pixels)).values()}
    others = [dict(flow_for_scene(sc, method=m, progress=False, max_pixels=run.cfg.flow_max_pixels)) for m in between_flow_methods(run.cfg)]
    print(f"{a.run}: step {run.step}, {len(run.gaussians)} Gaussians; load "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(f"{'frame':>5} {'model':>7} {'DIS':>7} {'target':>7} {'model~DIS':>10} {'model~target':>13}  (dB)")
    rows = []

    def sources(p):
        return [p, *extra_pairs(others, p)]

    for k in sc.test_indices:
        f = sc.frames[k]
        i0, i1, s = neighbours(sc, k)
        model = render(rt, params, f.camera, f.time).host()["image"]
        dis = baseline_images(sc, k)["dis"]
        pair = pairs.get(i0)
        bend = None
        if pair is not None and pair.dst == i1 and run.cfg.between_path == "quadratic":
            ordered = usable_pairs(sc, pairs)
            fused = run.cfg.between_flow_splat
            bend = pair_bend(sc, ordered, ordered.index(pair), sources,
                             (lambda i: consistent_flows(sources(ordered[i]))) if fused else None)
        target = (between_target(sc, pair, s, extra_pairs(others, pair), fuse=run.cfg.between_fuse,
                                 flow_splat=run.cfg.between_flow_splat, bend=bend)[0]
                  if pair is not None and pair.dst == i1 else None)
        r = [psnr(model, f.image), psnr(dis, f.image),
             np.nan if target is None else psnr(target, f.image),
             psnr(model, dis), np.nan if target is None else psnr(model, target)]
        rows.append(r)
        print(f"{k:>5} " + " ".join(f"{v:>{w}.2f}" for v, w in zip(r, (7, 7, 7, 10, 13))))
    m = np.nanmean(np.array(rows), axis=0)
    print(f"{'mean':>5} " + " ".join(f"{v:>{w}.2f}" for v, w in zip(m, (7, 7, 7, 10, 13))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
