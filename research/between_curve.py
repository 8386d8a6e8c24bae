"""How far a trained model is from its in-between teacher across a pair, not only at its middle
(research/QUALITY.md, finding 38).

    python research/between_curve.py RUN [--fractions 9] [--plain 8] [--per-pair]

For the training pairs around the run's scored frames (its validation or test frames: pairs two
frame spacings long) and for up to --plain pairs of adjacent training frames (one spacing), the PSNR
of the model's render at fraction s against the teacher's image there (train/between.py Teacher, the
static target, no model) and against the model's own renders at the pair's two frames blended
linearly (1 - s) R0 + s R1 (how far the render at s is from a cross-fade of its ends), per s on a
grid of --fractions points from 0 to 1.  s = 0 and 1 are the training frames themselves, where the
teacher is the frame.  Masks are applied as eval applies them.  Training frames only are read.
--per-pair also prints each pair around a scored frame on its own, with the mean flow magnitude
between its two frames (Teacher.motion), so that nearly still pairs can be told from moving ones.
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", help="a training run folder (config.json and a checkpoint)")
    ap.add_argument("--fractions", type=int, default=9, help="grid points from s=0 to s=1")
    ap.add_argument("--plain", type=int, default=8, help="adjacent training pairs to sample as well")
    ap.add_argument("--per-pair", action="store_true", help="also one row per pair around a scored frame")
    a = ap.parse_args(argv)
    from endowave_cl.baselines import neighbours, teacher_for
    from endowave_cl.errors import EndowaveError
    from endowave_cl.gaussians import upload
    from endowave_cl.metrics import psnr
    from endowave_cl.render import render
    from endowave_cl.run_io import load_run
    from endowave_cl.runtime import get_runtime
    from endowave_cl.train.between import pair_time
    rt = get_runtime()
    try:
        run = load_run(a.run)
    except EndowaveError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    sc = run.scene
    params = upload(rt, run.gaussians)
    teacher = teacher_for(sc)
    pairs = teacher.sampler.pairs

    def masked(k, img):
        m = sc.frames[k].mask
        return img if m is None else img * m[..., None]

    def view(camera, t):
        return np.clip(render(rt, params, camera, t, select=True).host()["image"], 0, 1)

    gap = {neighbours(sc, k)[:2] for k in sc.test_indices}
    around = [i for i, p in enumerate(pairs) if (p.src, p.dst) in gap]
    rest = [i for i, p in enumerate(pairs) if (p.src, p.dst) not in gap]
    rng = np.random.default_rng(0)
    plain = sorted(rng.choice(rest, size=min(a.plain, len(rest)), replace=False).tolist()) if rest else []
    grid = np.linspace(0.0, 1.0, a.fractions)
    print(f"{a.run}: {sc.split} frames, step {run.step}, {len(run.gaussians)} Gaussians; "
          f"{len(around)} pairs around scored frames, {len(plain)} adjacent pairs; load "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    for name, idx in (("around scored frames", around), ("adjacent", plain)):
        if not idx:
            continue
        vs_teacher = np.zeros((len(idx), len(grid)))
        vs_fade = np.zeros_like(vs_teacher)
        for r, i in enumerate(idx):
            p = pairs[i]
            cam = sc.frames[p.src].camera
            ends = [masked(p.src, view(cam, pair_time(sc, p, 0.0))), masked(p.src, view(cam, pair_time(sc, p, 1.0)))]
            for c, s in enumerate(grid):
                model = masked(p.src, view(cam, pair_time(sc, p, float(s))))
                vs_teacher[r, c] = psnr(model, masked(p.src, teacher.image(p.src, p.dst, float(s))))
                vs_fade[r, c] = psnr(model, (1.0 - s) * ends[0] + s * ends[1])
        print(f"  {name} ({len(idx)} pairs)")
        print("    s              " + " ".join(f"{s:>6.3f}" for s in grid))
        print("    model~teacher  " + " ".join(f"{v:>6.2f}" for v in vs_teacher.mean(0)))
        print("    model~fade     " + " ".join(f"{v:>6.2f}" for v in vs_fade.mean(0)))
        if a.per_pair and name.startswith("around"):
            for r, i in enumerate(idx):
                p = pairs[i]
                print(f"    {p.src:>3}-{p.dst:<3} {teacher.motion(p.src, p.dst):5.2f} px "
                      + " ".join(f"{v:>6.2f}" for v in vs_teacher[r]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
