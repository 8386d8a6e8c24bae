"""Whether frames further away in time add anything to the two-frame prediction of an unseen frame
(research/QUALITY.md, finding 50): no model, the scenes' validation frames only.

    python research/temporal_window.py [--shared ../shared] [--scenes pulling,traction,pushing]

For each validation frame v whose neighbours v - 1 and v + 1 and whose next frames out v - 2 and
v + 2 are training frames, scored against frame v (PSNR, whole image):

- teacher: the in-between teacher of the pair (v - 1, v + 1) at its middle (baselines.teacher_for);
- dis1:    the DIS interpolation with bicubic warps from the same pair;
- dis2:    the same from the wider pair (v - 2, v + 2), what a window of five frames adds;
- blends:  the teacher with dis2 (3:1, 2:1, 1:1) and with dis1 (1:1).

If the frames' codec noise were a large share of the teacher's error on nearly still frames, a
blend with the wider pair would lower it there (independent noise averages out).  Rows are grouped
by the motion between the pair's frames (Teacher.motion).  Frame v itself is read only as the truth.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

SCENES = {"pulling": ("data/endonerf/pulling_soft_tissues", 2.0),
          "traction": ("data/endonerf_clips/traction", 1.0),
          "pushing": ("data/endonerf_clips/pushing", 1.0)}
BINS = (0.0, 1.0, 2.0, 4.0, np.inf)   # px between the pair's frames
COLUMNS = ("teacher", "dis1", "dis2", "t3_dis2", "t2_dis2", "t1_dis2", "t1_dis1")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--shared", default=str(Path(__file__).resolve().parents[1].parent / "shared"))
    ap.add_argument("--scenes", default=",".join(SCENES))
    a = ap.parse_args(argv)
    from endowave_cl.baselines import dis_interpolations, neighbours, teacher_for
    from endowave_cl.data.scene import apply_split, load_scene
    from endowave_cl.metrics import psnr

    rows = []
    for name in [s for s in a.scenes.split(",") if s]:
        rel, down = SCENES[name]
        path = Path(a.shared) / rel
        if not path.is_dir():
            print(f"{name}: {path} not found, skipped")
            continue
        scene = apply_split(load_scene(path, downscale=down), "validation")
        teacher = teacher_for(scene)
        train = set(scene.train_indices)
        for v in scene.test_indices:
            i0, i1, frac = neighbours(scene, v)
            if (i0, i1) != (v - 1, v + 1) or not {v - 2, v + 2} <= train:
                continue
            im = {k: scene.frames[k].image for k in (v - 2, v - 1, v + 1, v + 2)}
            t = teacher.image(i0, i1, frac)
            d1 = dis_interpolations(im[v - 1], im[v + 1], 0.5, samplers=("cubic",))["cubic"]
            d2 = dis_interpolations(im[v - 2], im[v + 2], 0.5, samplers=("cubic",))["cubic"]
            preds = {"teacher": t, "dis1": d1, "dis2": d2, "t3_dis2": 0.75 * t + 0.25 * d2,
                     "t2_dis2": (2 * t + d2) / 3, "t1_dis2": 0.5 * (t + d2), "t1_dis1": 0.5 * (t + d1)}
            truth = scene.frames[v].image
            r = {"scene": name, "frame": v, "motion": float(teacher.motion(i0, i1))}
            r.update({k: psnr(p, truth) for k, p in preds.items()})
            rows.append(r)
            print(f"{name:<9} {v:>4} {r['motion']:6.2f} px " + " ".join(f"{k} {r[k]:6.2f}" for k in COLUMNS), flush=True)
    if not rows:
        print("no frames scored")
        return 1
    print("\nmeans (dB) by scene and by motion between the pair's frames")
    groups = [(n, [r for r in rows if r["scene"] == n]) for n in dict.fromkeys(r["scene"] for r in rows)]
    groups += [(f"{lo:g}-{hi:g} px", [r for r in rows if lo <= r["motion"] < hi]) for lo, hi in zip(BINS[:-1], BINS[1:])]
    print(f"{'group':<12} {'n':>3} " + " ".join(f"{c:>8}" for c in COLUMNS))
    for label, rs in groups:
        if rs:
            print(f"{label:<12} {len(rs):>3} " + " ".join(f"{np.mean([r[c] for r in rs]):8.2f}" for c in COLUMNS))
    return 0


if __name__ == "__main__":
    sys.exit(main())
