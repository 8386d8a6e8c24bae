"""How much the average of several trained models' renders gains at the scored frames over each
model alone (research/QUALITY.md, finding 50): whether the part of a model's error that is its own
(its departure from its teacher) differs between seeds and so averages out.

    python research/seed_ensemble.py RUN [RUN ...] [--lpips]

RUNs: training runs of one scene and split (validation or test) with their checkpoints kept
(`tools/validate.py --keep-checkpoints`), usually the same settings at different seeds.  At each
scored frame every model is rendered alone (nothing reads a frame), the renders are averaged, and
each model, the average and the in-between teacher are scored with metrics.frame_scores (the
function eval uses), grouped by the motion between the frame's two training neighbours.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

BINS = (0.0, 1.0, 2.0, 4.0, np.inf)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="training run folders (config.json and a checkpoint)")
    ap.add_argument("--lpips", action="store_true", help="LPIPS too (needs the weights installed)")
    a = ap.parse_args(argv)
    from endowave_cl.baselines import baseline_images, neighbours, teacher_for
    from endowave_cl.errors import EndowaveError
    from endowave_cl.gaussians import upload
    from endowave_cl.metrics import frame_scores
    from endowave_cl.render import render
    from endowave_cl.run_io import load_run
    from endowave_cl.runtime import get_runtime
    rt = get_runtime()
    try:
        runs = [load_run(r) for r in a.runs]
    except EndowaveError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    sc = runs[0].scene
    for r, path in zip(runs[1:], a.runs[1:]):
        if r.scene.test_indices != sc.test_indices or (r.scene.width, r.scene.height) != (sc.width, sc.height):
            print(f"error: {path} scores other frames or another size than {a.runs[0]}", file=sys.stderr)
            return 2
    params = [upload(rt, r.gaussians) for r in runs]
    teacher = teacher_for(sc)
    names = [f"model {i}" for i in range(len(runs))] + ["average", "teacher"]
    rows = []
    for k in sc.test_indices:
        f = sc.frames[k]
        i0, i1, _ = neighbours(sc, k)
        renders = [np.clip(render(rt, p, f.camera, f.time, select=True).host()["image"], 0, 1) for p in params]
        preds = renders + [np.mean(renders, axis=0), baseline_images(sc, k, teacher)["teacher"]]
        scores = [frame_scores(p, f.image, f.mask, a.lpips) for p in preds]
        rows.append((k, teacher.motion(i0, i1) or 0.0, scores))
        print(f"frame {k:>4} {rows[-1][1]:5.2f} px " + " ".join(f"{n} {s['psnr']:6.2f}" for n, s in zip(names, scores)),
              flush=True)
    print(f"\n{sc.split} frames of {sc.path}, {len(runs)} models; mean PSNR (dB)" + (" / LPIPS" if a.lpips else ""))
    groups = [("all", rows)] + [(f"{lo:g}-{hi:g} px", [r for r in rows if lo <= r[1] < hi])
                                for lo, hi in zip(BINS[:-1], BINS[1:])]
    print(f"{'frames':<10} {'n':>3} " + " ".join(f"{n:>15}" for n in names))
    for label, rs in groups:
        if not rs:
            continue
        cells = []
        for j in range(len(names)):
            p = np.mean([r[2][j]["psnr"] for r in rs])
            cells.append(f"{p:6.2f}" + (f" / {np.mean([r[2][j]['lpips'] for r in rs]):.4f}" if a.lpips else ""))
        print(f"{label:<10} {len(rs):>3} " + " ".join(f"{c:>15}" for c in cells))
    return 0


if __name__ == "__main__":
    sys.exit(main())
