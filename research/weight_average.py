"""How much the parameters averaged over a run's last steps gain over its last step (stochastic
weight averaging; train/average.py, the `average_last` setting), for several windows in one run.

    python research/weight_average.py SCENE --out RUN --minutes 6 --downscale 2 --validation \
        --windows 0.1,0.2,0.3,0.5 [--seed 0] [--lpips] [--set KEY=VALUE ...]

One training run (the settings of `endowave-cl train` with the same options, but average_last 0:
the run itself saves its last step) keeps one running mean per window (the parameters at
every train/average.py AVERAGE_EVERY-th step of the last fraction of the steps, never before
densify_until); at the end the last step and each mean are scored on the run's scored frames
(validation frames with --validation) with evaluate_run, the function eval uses.  Each mean costs
one pass over the parameters per AVERAGE_EVERY steps, so the run takes slightly fewer steps in a
time budget than the defaults would; the comparison is within the one trajectory, paired.
Writes RUN/weight_average.json.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    from endowave_cl.commands import train as train_cmd
    train_cmd.add_arguments(ap)
    ap.add_argument("--windows", default="0.1,0.2,0.3,0.5", help="fractions of the steps, comma-separated")
    ap.add_argument("--lpips", action="store_true", help="LPIPS too (needs the weights installed)")
    a = ap.parse_args(argv)
    windows = [float(w) for w in a.windows.split(",")]

    import numpy as np

    from endowave_cl.data.scene import apply_split, load_scene
    from endowave_cl.evaluation import evaluate_run
    from endowave_cl.runtime import get_runtime
    from endowave_cl.train.average import ParameterAverage, average_start
    from endowave_cl.train.trainer import Trainer

    cfg = train_cmd.build_config(a).replace(average_last=0.0)   # the windows below stand in for it
    scene = apply_split(load_scene(Path(a.scene), downscale=cfg.downscale, use_depth=cfg.use_depth), cfg.split)
    if not scene.has_depth:
        cfg = cfg.replace(use_depth=False)
    rt = get_runtime(getattr(a, "device", None))

    class WindowTrainer(Trainer):
        """The trainer with one running mean per window; the run saves its last step."""
        means = {}

        def average_step(self):
            for w in windows:
                if self.step < average_start(self.cfg.replace(average_last=w)):
                    continue
                m = self.means.get(w)
                if m is None:
                    self.means[w] = ParameterAverage(self.rt, self.params, self.step)
                elif m.due(self.step):
                    m.add(self.params)

        def set_gaussians(self, g, source_index):
            super().set_gaussians(g, source_index)
            self.means.clear()

    trainer = WindowTrainer(scene, cfg, Path(a.out), rt, resume=False, progress=not a.quiet)
    trainer.train(progress=not a.quiet)

    def score(params):
        m = evaluate_run(rt, params, scene, fps_runs=0, with_lpips=a.lpips)
        return {"psnr": m["psnr"], "ssim": m["ssim"], "lpips": m.get("lpips"),
                "per_frame": [f["model"]["psnr"] for f in m["per_frame"]]}

    rows = {"last step": score(trainer.params)}
    for w in windows:
        m = trainer.means.get(w)
        if m is None:
            continue
        rows[f"last {w:g} ({m.count} snapshots from step {m.first})"] = score(m.mean)
    base = np.array(rows["last step"]["per_frame"])
    print(f"{scene.path.name} ({scene.split} frames, {trainer.step} steps, seed {cfg.seed}):")
    for name, r in rows.items():
        d = np.array(r["per_frame"]) - base
        lp = "" if r["lpips"] is None else f"  LPIPS {r['lpips']:.4f}"
        print(f"  {name:<40} PSNR {r['psnr']:.3f}  SSIM {r['ssim']:.4f}{lp}  "
              f"per frame {d.min():+.3f} .. {d.max():+.3f}, better on {int((d > 0).sum())} of {len(d)}")
    Path(a.out, "weight_average.json").write_text(json.dumps({"steps": trainer.step, "seed": cfg.seed,
                                                              "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
