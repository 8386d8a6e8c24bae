"""Where a model loses at its unseen frames: its own fit at the two training frames around each
one, against what it renders between them and against its in-between teacher (research/QUALITY.md,
finding 34).

    python research/neighbour_fit.py RUN [RUN ...]

Per scored frame k (the run's split: its validation or its test frames), with training neighbours
k0 and k1: PSNR against the truth of the model at k, of the model at k0 and k1 (its fit there), of
the teacher (train/between.py Teacher: the static in-between target at k, no model) and of the
better of the two neighbours copied unchanged; and the PSNR of the model's render at k against the
teacher's image (how well the model reproduces what it is taught there).  A model whose scored
frames sit far below its fit at their neighbours loses between its training times, not at them.
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="training run folders (config.json and a checkpoint)")
    a = ap.parse_args(argv)
    from endowave_cl.baselines import neighbours, teacher_for
    from endowave_cl.errors import EndowaveError
    from endowave_cl.gaussians import upload
    from endowave_cl.metrics import psnr
    from endowave_cl.render import render
    from endowave_cl.run_io import load_run
    from endowave_cl.runtime import get_runtime
    rt = get_runtime()
    for path in a.runs:
        try:
            run = load_run(path)
        except EndowaveError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        sc = run.scene
        params = upload(rt, run.gaussians)
        teacher = teacher_for(sc)

        def masked(k, img):   # [H, W, 3]: scored as eval scores it (the tool mask's pixels zeroed)
            m = sc.frames[k].mask
            return img if m is None else img * m[..., None]

        def view(k):
            f = sc.frames[k]
            return masked(k, np.clip(render(rt, params, f.camera, f.time, select=True).host()["image"], 0, 1))

        print(f"{path}: {sc.split} frames, step {run.step}, {len(run.gaussians)} Gaussians; load "
              f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}")
        cols = ("model", "fit k0", "fit k1", "teacher", "copy", "model~teacher")
        print(f"{'frame':>5} " + " ".join(f"{c:>13}" for c in cols) + "  (dB)")
        rows = []
        for k in sc.test_indices:
            i0, i1, s = neighbours(sc, k)
            truth = masked(k, sc.frames[k].image)
            model = view(k)
            taught = masked(k, teacher.image(i0, i1, s))
            r = [psnr(model, truth), psnr(view(i0), masked(i0, sc.frames[i0].image)),
                 psnr(view(i1), masked(i1, sc.frames[i1].image)), psnr(taught, truth),
                 max(psnr(masked(k, sc.frames[i].image), truth) for i in (i0, i1)), psnr(model, taught)]
            rows.append(r)
            print(f"{k:>5} " + " ".join(f"{v:>13.2f}" for v in r))
        m = np.mean(np.array(rows), axis=0)
        print(f"{'mean':>5} " + " ".join(f"{v:>13.2f}" for v in m))
        print(f"model minus its fit at the neighbours: {m[0] - 0.5 * (m[1] + m[2]):+.2f} dB; "
              f"teacher minus it: {m[3] - 0.5 * (m[1] + m[2]):+.2f} dB\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
