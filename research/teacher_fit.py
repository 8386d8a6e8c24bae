"""How closely a trained model follows its in-between target at the test frames (research/QUALITY.md
finding 28).

    python research/teacher_fit.py RUN

For every test frame k between training frames k - 1 and k + 1 it prints PSNR (dB) of: the model
against the real frame; the run's in-between target at s = 0.5 (train/between.py between_target
with the run's own keys, the flows estimated as training estimates them, flow_max_pixels
included, the pair's paths bent by the training frames beyond it with between_path "quadratic", and
the model's motion) against the real frame; the model against that target; the
cross-fade of the model's renders at k - 1 and k + 1 against the real frame and against the
model at k; the neighbour mean; and the model at k - 1 and k + 1.
"""
from __future__ import annotations

import sys
from types import SimpleNamespace

import numpy as np


def main(argv=None) -> int:
    from endowave_cl.data.flow import estimate_flow_at, estimation_size
    from endowave_cl.errors import EndowaveError
    from endowave_cl.gaussians import upload
    from endowave_cl.metrics import psnr
    from endowave_cl.render import render
    from endowave_cl.run_io import load_run
    from endowave_cl.runtime import get_runtime
    from endowave_cl.train.between import bend_around, between_target
    from endowave_cl.train.config import between_flow_methods
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1 or argv[0].startswith("-"):
        print(__doc__.split("\n\n")[1].strip(), file=sys.stderr)
        return 2
    try:
        run = load_run(argv[0])
    except EndowaveError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    sc, c = run.scene, run.cfg
    rt = get_runtime()
    params = upload(rt, run.gaussians)
    methods = sorted({c.flow_method, *between_flow_methods(c)})
    size = estimation_size(sc.width, sc.height, c.flow_max_pixels)

    def est(a, b, m):   # as data/flow.py estimates a training pair's flow
        return estimate_flow_at(a, b, m, size)

    def draw(cam, t, t_flow=None):
        return render(rt, params, cam, t, t_flow, select=True).host()

    print(f"{argv[0]}: step {run.step}, {len(run.gaussians)} Gaussians")
    print("frame  model  target  model~target  crossfade  model~crossfade  neighbour-mean  model(k-1) model(k+1)")
    rows = []
    for k in sc.test_indices:
        if k - 1 < 0 or k + 1 >= len(sc.frames):
            continue
        f0, f, f1 = sc.frames[k - 1], sc.frames[k], sc.frames[k + 1]
        flows = {m: SimpleNamespace(src=k - 1, dst=k + 1, flow=est(f0.image, f1.image, m),
                                    flow_bw=est(f1.image, f0.image, m)) for m in methods}
        t = 0.5 * (float(f0.time) + float(f1.time))
        disp = draw(f0.camera, t, float(f0.time))["flow"]
        fwd = (draw(f0.camera, float(f0.time), t)["flow"], draw(f1.camera, float(f1.time), t)["flow"])
        order = [c.flow_method] + [m for m in between_flow_methods(c) if m != c.flow_method]
        bend = (bend_around(sc, [flows[m] for m in order], order, lambda a, b, m: est(sc.frames[a].image, sc.frames[b].image, m),
                            c.between_flow_splat)
                if c.between_path == "quadratic" else None)
        target = np.clip(between_target(sc, flows[c.flow_method], 0.5, [flows[m] for m in order[1:]], disp,
                                        c.between_model, c.between_fuse, fwd if c.between_model_splat else None,
                                        c.between_flow_splat, bend=bend)[0], 0, 1)
        m, m0, m1 = (draw(x.camera, x.time)["image"] for x in (f, f0, f1))
        cross = 0.5 * (m0 + m1)
        row = [psnr(m, f.image), psnr(target, f.image), psnr(m, target), psnr(cross, f.image), psnr(m, cross),
               psnr(0.5 * (f0.image + f1.image), f.image), psnr(m0, f0.image), psnr(m1, f1.image)]
        rows.append(row)
        print(f"{k:5d}  " + "  ".join(f"{x:6.2f}" for x in row))
    if rows:
        print(" mean  " + "  ".join(f"{x:6.2f}" for x in np.mean(rows, 0)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
