"""Score in-between targets as interpolators, with a trained model's motion (research/QUALITY.md,
findings 20-21).

    python research/teacher_probe.py RUN [--variant NAME:KEY=VALUE,KEY=VALUE ...]

The target a late in-between step trains on (train/between.py between_target: the flow
hypotheses and the model's motion, as the run's config says) is built at fraction s = 0.5 for two
sets of frames and scored against the real frame (PSNR, dB):

- test: every test frame k between training frames k - 1 and k + 1 (the model never saw k);
- triplets: every third training frame k whose neighbours k - 1 and k + 1 are training frames
  too, predicted from those two.  The flows of the pair (k - 1, k + 1) are estimated here (it is
  not a training pair), so the flow half never saw k; the model did, so its half is optimistic.
  The triplets are a check that uses no test frame.

Each variant changes in-between keys of the run's config (between_fuse, between_flow_splat,
between_model, between_model_splat, between_flows, between_path: with "quadratic" the flows to the
nearest training frames beyond the pair are estimated here too); the model itself is the run's.  Prints the model's own render too.
"""
from __future__ import annotations

import argparse
import os
import sys
from types import SimpleNamespace

import numpy as np

KEYS = ("between_fuse", "between_flow_splat", "between_model", "between_model_splat", "between_flows", "between_path")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", help="a training run folder (config.json and a checkpoint)")
    ap.add_argument("--variant", action="append", default=[], metavar="NAME:KEY=VALUE,...",
                    help=f"a target with these in-between keys changed ({', '.join(KEYS)}); repeatable")
    a = ap.parse_args(argv)
    from endowave_cl.data.flow import estimate_flow
    from endowave_cl.errors import EndowaveError
    from endowave_cl.gaussians import upload
    from endowave_cl.metrics import psnr
    from endowave_cl.render import render
    from endowave_cl.run_io import load_run
    from endowave_cl.runtime import get_runtime
    from endowave_cl.train.between import bend_around, between_target
    from endowave_cl.train.config import between_flow_methods, with_values
    try:
        run = load_run(a.run)
        variants = {"run's config": run.cfg}
        for v in a.variant:
            name, _, body = v.partition(":")
            values = dict(item.split("=", 1) for item in body.split(",") if item.strip())
            if not name or not values or any(k.strip() not in KEYS for k in values):
                raise EndowaveError(f"--variant {v!r}: expected NAME:KEY=VALUE,... with keys from {', '.join(KEYS)}")
            variants[name] = with_values(run.cfg, {k.strip(): x.strip() for k, x in values.items()},
                                         f"--variant {name}", from_text=True)
    except (EndowaveError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    sc = run.scene
    rt = get_runtime()
    params = upload(rt, run.gaussians)
    methods = sorted({m for c in variants.values() for m in [c.flow_method] + between_flow_methods(c)})
    train = set(sc.train_indices)
    sets = {"test": [k for k in sc.test_indices if {k - 1, k + 1} <= train],
            "triplets": [k for k in range(1, len(sc.frames) - 1) if {k - 1, k, k + 1} <= train][::3]}
    print(f"{a.run}: step {run.step}, {len(run.gaussians)} Gaussians; load "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}; s = 0.5")
    cache = {}

    def estimated(i, j, m):
        """frame i's flow to frame j by estimator m, estimated once"""
        if (i, j, m) not in cache:
            cache[(i, j, m)] = estimate_flow(sc.frames[i].image, sc.frames[j].image, m)
        return cache[(i, j, m)]

    for set_name, frames in sets.items():
        scores = {name: [] for name in ["model", *variants]}
        for k in frames:
            f0, f, f1 = sc.frames[k - 1], sc.frames[k], sc.frames[k + 1]
            flows = {m: SimpleNamespace(src=k - 1, dst=k + 1, flow=estimate_flow(f0.image, f1.image, m),
                                        flow_bw=estimate_flow(f1.image, f0.image, m)) for m in methods}
            t = 0.5 * (float(f0.time) + float(f1.time))

            def motion(camera, t_at, t_to):
                return render(rt, params, camera, t_at, t_to).host()["flow"]
            disp = motion(f0.camera, t, float(f0.time))
            fwd = (motion(f0.camera, float(f0.time), t), motion(f1.camera, float(f1.time), t))
            scores["model"].append(psnr(render(rt, params, f.camera, f.time).host()["image"], f.image))
            for name, c in variants.items():
                order = [c.flow_method] + between_flow_methods(c)
                bend = (bend_around(sc, [flows[m] for m in order], order, estimated,
                                    c.between_flow_splat)
                        if c.between_path == "quadratic" else None)
                image = between_target(sc, flows[c.flow_method], 0.5, [flows[m] for m in order[1:]], disp,
                                       c.between_model, c.between_fuse, fwd if c.between_model_splat else None,
                                       c.between_flow_splat, bend=bend)[0]
                scores[name].append(psnr(np.clip(image, 0, 1), f.image))
        print(f"{set_name} ({len(frames)} frames: {' '.join(map(str, frames))})")
        for name, v in scores.items():
            print(f"  {name:<28} {np.mean(v):7.3f}   " + " ".join(f"{x:.2f}" for x in v))
    return 0


if __name__ == "__main__":
    sys.exit(main())
