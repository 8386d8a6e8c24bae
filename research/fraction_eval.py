"""A trained synthetic run rendered at times between its frames, against the exact frames there.

    python research/fraction_eval.py RUN [--factor 4] [--json FILE]

The test frames of a scene sit half-way between two training frames, so eval scores a model at
one place in a pair only.  A synthetic scene (data/synth.py, whose motion is a function of time in
[0, 1]) is generated again with FACTOR times as many frames, from the same parameters (its
scene.json); every new time that is not a training frame's is rendered by the run's model and
scored against the exact frame there.  The times are grouped by their distance to the nearest
training frame, in frame spacings of the original scene (0.25, 0.5, ... with factor 4; the
held-out frames themselves are 1.0 away), beside the cross-fade of the two training frames around
each time, by the time's fraction between them.

Prints per distance the means of eval's figures (metrics.frame_scores: PSNR of the masked images,
PSNR on tissue pixels only, SSIM) for the model and the cross-fade; --json writes the same figures.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile

import numpy as np


def main(argv=None) -> int:
    from endowave_cl.data.scene import load_scene
    from endowave_cl.data.synth import make_synthetic_scene
    from endowave_cl.errors import EndowaveError
    from endowave_cl.gaussians import upload
    from endowave_cl.metrics import frame_scores
    from endowave_cl.render import render
    from endowave_cl.run_io import load_run
    from endowave_cl.runtime import get_runtime

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run")
    ap.add_argument("--factor", type=int, default=4, help="times as many frames (default 4)")
    ap.add_argument("--json", help="write the figures to this file")
    args = ap.parse_args(argv)
    if args.factor < 2:
        print("error: --factor must be at least 2", file=sys.stderr)
        return 2
    try:
        run = load_run(args.run)
        info_file = os.path.join(str(run.scene.path), "scene.json")
        try:
            with open(info_file) as f:
                p = json.load(f)["params"]
            width, height, frames = int(p["width"]), int(p["height"]), int(p["frames"])
            seed, deformation = int(p["seed"]), float(p["deformation"])
        except (OSError, ValueError, KeyError, TypeError):
            raise EndowaveError(f"{info_file}: not a synthetic scene's description (data/synth.py)") from None
    except EndowaveError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    sc, F = run.scene, args.factor
    train_times = np.array(sorted(float(sc.frames[k].time) for k in sc.train_indices))   # [T]
    rt = get_runtime()
    params = upload(rt, run.gaussians)
    groups = {}   # distance (spacings) -> {figure: [one value per time]}
    with tempfile.TemporaryDirectory() as tmp:
        dense_path = make_synthetic_scene(os.path.join(tmp, "dense"), width=width, height=height,
                                          frames=(frames - 1) * F + 1, seed=seed, deformation=deformation)
        dense = load_scene(dense_path, downscale=run.cfg.downscale, world_scale=sc.world_scale)   # the run's units
        by_time = {round(float(f.time) * (frames - 1), 9): f for f in sc.frames}
        for j, f in enumerate(dense.frames):
            if j % F == 0 and sc.frames[j // F].index in sc.train_indices:
                continue                                         # a training frame itself
            t = float(f.time)
            i1 = int(np.searchsorted(train_times, t))
            if i1 == 0 or i1 >= len(train_times):
                continue                                         # before the first / after the last
            t0, t1 = train_times[i1 - 1], train_times[i1]
            d = round(min(t - t0, t1 - t) * (frames - 1) * F) / F
            s = (t - t0) / (t1 - t0)
            a, b = by_time[round(t0 * (frames - 1), 9)], by_time[round(t1 * (frames - 1), 9)]
            img = render(rt, params, f.camera, t, select=True).host()["image"]
            cross = ((1.0 - s) * a.image + s * b.image).astype(np.float32)
            g = groups.setdefault(d, {k: [] for k in ("psnr", "psnr_masked", "ssim", "crossfade_psnr",
                                                      "crossfade_psnr_masked", "s")})
            m, c = frame_scores(img, f.image, f.mask), frame_scores(cross, f.image, f.mask)
            for k in ("psnr", "psnr_masked", "ssim"):
                g[k].append(m[k])
            g["crossfade_psnr"].append(c["psnr"])
            g["crossfade_psnr_masked"].append(c["psnr_masked"])
            g["s"].append(s)
    print(f"{args.run}: step {run.step}, {len(run.gaussians)} Gaussians; synthetic {width}x{height}, "
          f"{frames} frames, generated again with {(frames - 1) * F + 1}")
    print("distance to the nearest training frame (spacings)  times   PSNR  masked    SSIM  cross-fade PSNR / masked")
    out = {}
    for d in sorted(groups):
        g = groups[d]
        row = {k: float(np.mean(v)) for k, v in g.items() if k != "s"}
        row["times"] = len(g["psnr"])
        out[f"{d:g}"] = row
        print(f"{d:>48g}  {row['times']:5d}  {row['psnr']:5.2f}  {row['psnr_masked']:6.2f}  {row['ssim']:6.4f}"
              f"  {row['crossfade_psnr']:6.2f} / {row['crossfade_psnr_masked']:.2f}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"run": args.run, "step": run.step, "factor": F, "by_distance": out}, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
