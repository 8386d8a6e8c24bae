#!/usr/bin/env python
"""Seconds per training step (render, losses, adjoints, Adam) at 640x512 with 100,000 Gaussians.

Uses the shared real EndoNeRF frames when present (../shared/data/endonerf/pulling_soft_tissues),
else a synthetic scene of the same size. Prints the median over --runs steps after --warmup steps,
with the per-part split (each part followed by a queue finish; project_bwd is timed inside the
adjoints, guard is the gradients' NaN / Inf check), the device and the sizes; then
the median of as many Trainer.train_step calls (the step as training runs it: no finish between
the parts, its own read-backs and the NaN guard), and of as many Trainer.train_step_between calls
(an in-between step, with the host's part of it: drawing and warping its target), and of as many
in-between steps as they run after densify_until (with between_model: the forward read back and
the model's motion warped into the target; with between_model_splat two more renders at the pair's
frames and the frames splatted forward along them; with between_motion_refresh that motion is
timed both rendered afresh, as in the step that first draws a pair, and kept from an earlier step).

    python benchmarks/bench_train_step.py [--gaussians 100000] [--runs 10] [--downscale 2] [--no-flow] [--no-wavelet]
                                     [--checkpoint RUN/checkpoint_0003000.npz] [--no-adam-skip-culled] [--kernels [--top N]]

--checkpoint takes the Gaussians of a trained model instead (a real run's count, and Gaussians that
live only part of the sequence: most of them are culled at any one time), with fresh Adam moments.

--downscale 2 trains on the frames at half size (320x256 for EndoNeRF), with the same number of
Gaussians.
"""
from __future__ import annotations

import argparse
import os
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

SHARED_SCENE = Path(__file__).resolve().parents[2] / "shared" / "data" / "endonerf" / "pulling_soft_tissues"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default=str(SHARED_SCENE))
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--downscale", type=float, default=1.0, help="frame size divisor (2: 320x256)")
    ap.add_argument("--no-flow", action="store_true")
    ap.add_argument("--no-wavelet", action="store_true")
    ap.add_argument("--full-sh", action="store_true",
                    help="per-part steps: the adjoint writes v_sh in full for Adam and the NaN guard "
                         "(the training step passes it as factors)")
    ap.add_argument("--adam-skip-culled", action=argparse.BooleanOptionalAction, default=None,
                    help="Adam leaves the step's culled Gaussians alone, and the steps render only the "
                         "Gaussians alive at their time (config key adam_skip_culled; default: the "
                         "config's, as training runs; --no-adam-skip-culled: every Gaussian)")
    ap.add_argument("--sh-degree", type=int, default=None,
                    help="the config's sh_degree (0..3; default: the config default, resolved for the scene)")
    ap.add_argument("--checkpoint", help="a trained model's checkpoint (.npz): its Gaussians instead of new ones")
    ap.add_argument("--no-select", action="store_true",
                    help="every step over every Gaussian (sets $ENDOWAVE_NO_SELECT); by default, with "
                         "adam_skip_culled (the config default), the steps render and differentiate only those alive at "
                         "their time, as training does (ops/select.py)")
    ap.add_argument("--kernels", action="store_true",
                    help="also print each part's summed kernel time (OpenCL event profiling of the "
                         "Runtime's launches) and the step's slowest kernels: wall time far above "
                         "kernel time means the host (launches, read-backs) is what the step waits for")
    ap.add_argument("--top", type=int, default=8, help="how many of the slowest kernels --kernels prints")
    ap.add_argument("--device", default=None)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="change a training config key (endowave_cl/train/config.py), e.g. --set between_flow_splat=true")
    args = ap.parse_args(argv)

    from endowave_cl.data.scene import load_scene
    from endowave_cl.ops.util import nonfinite_flag
    from endowave_cl.render import render, render_backward
    from endowave_cl.runtime import get_runtime
    from endowave_cl.train.config import TrainConfig
    from endowave_cl.train.trainer import Trainer

    scene_path = Path(args.scene)
    if not (scene_path / "poses_bounds.npy").is_file():
        from endowave_cl.data.synth import make_synthetic_scene
        scene_path = Path(tempfile.mkdtemp()) / "synthetic_640"
        print(f"shared frames absent: generating a synthetic 640x512 scene in {scene_path}")
        make_synthetic_scene(scene_path, width=640, height=512, frames=16, seed=0)
    scene = load_scene(scene_path, downscale=args.downscale)
    rt = get_runtime(args.device)
    events = None
    if args.kernels:
        sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
        from kernel_events import kernel_ms, profile_launches
        events = profile_launches(rt)   # before the trainer's first buffer
    cfg = TrainConfig(iterations=10**6, init_points=args.gaussians, use_flow=not args.no_flow,
                      use_wavelet=not args.no_wavelet, eval_every=0, checkpoint_every=0,
                      **({} if args.adam_skip_culled is None else {"adam_skip_culled": args.adam_skip_culled}))
    if args.sh_degree is not None:
        cfg = cfg.replace(sh_degree=args.sh_degree)
    if args.set:
        from endowave_cl.train.config import with_values
        cfg = with_values(cfg, dict(item.split("=", 1) for item in args.set), "--set", from_text=True)
    if args.no_select:
        from endowave_cl.ops.select import ENV_NO_SELECT
        os.environ[ENV_NO_SELECT] = "1"
    with tempfile.TemporaryDirectory() as run:
        tr = Trainer(scene, cfg, run, rt, log=lambda s: None, resume=False)
        if args.checkpoint:
            import numpy as np
            from endowave_cl.checkpoint import load_checkpoint
            g = load_checkpoint(args.checkpoint)["gaussians"]
            tr.set_gaussians(g, np.full(len(g), -1))   # fresh (zero) Adam moments
        n = len(tr.params["means"])
        print(f"device: {rt.describe()}")
        print(f"scene: {scene_path} ({scene.width}x{scene.height}), {n} Gaussians, losses: rgb"
              f"{', depth' if cfg.use_depth and scene.has_depth else ''}{', flow' if cfg.use_flow else ''}"
              f"{', wavelet' if cfg.use_wavelet else ''}; median of {args.runs} steps after {args.warmup}")
        parts = {"render": [], "losses": [], "backward": [], "project_bwd": [], "guard": [], "adam": [],
                 "step": []}   # project_bwd: part of backward
        cpu = []   # CPU seconds per step, all threads (moves much less than wall time under load)
        kparts = {key: [] for key in ("render", "losses", "backward", "guard", "adam", "step")}
        kernels = {}   # kernel name -> [ms per step]

        def cpu_s():
            r = resource.getrusage(resource.RUSAGE_SELF)
            return r.ru_utime + r.ru_stime
        order = list(scene.train_indices)
        select = tr.select_live   # Trainer.train_step below makes the same choice
        for i in range(args.warmup + args.runs):
            k = order[i % len(order)]
            f, tgt = scene.frames[k], tr.targets[k]
            rt.queue.finish()
            if events is not None:
                events.clear()
            marks = []   # events launched before each part's end
            c0 = cpu_s()
            t0 = time.perf_counter()
            out = render(rt, tr.params, f.camera, f.time, tgt.next_time, select=select)
            rt.queue.finish()
            t1 = time.perf_counter()
            marks.append(len(events or ()))
            total, _, v = tr.losses_and_gradient(out, tgt)
            rt.queue.finish()
            t2 = time.perf_counter()
            marks.append(len(events or ()))
            grads = render_backward(rt, tr.params, out, v, densify_stats=tr.stats, timed=True,
                                    sh_factors=not args.full_sh)
            rt.queue.finish()
            t3 = time.perf_counter()
            marks.append(len(events or ()))
            nonfinite_flag(rt, grads.values()).get()   # the NaN guard's check (train_step reads it with the sums)
            t3g = time.perf_counter()
            marks.append(len(events or ()))
            tr.adam.step({name[2:]: v for name, v in grads.items()}, tr.group_lrs(0),
                         visible=out.proj.radius if cfg.adam_skip_culled else None,
                         rows=None if out.live is None else out.live.rows)
            rt.queue.finish()
            t4 = time.perf_counter()
            marks.append(len(events or ()))
            if i >= args.warmup and events is not None:
                lo = 0
                for key, hi in zip(("render", "losses", "backward", "guard", "adam"), marks):
                    kparts[key].append(sum(kernel_ms(events[lo:hi]).values()) * 1e-3)
                    lo = hi
                kparts["step"].append(sum(kernel_ms(events).values()) * 1e-3)
                for name, ms in kernel_ms(events).items():
                    kernels.setdefault(name, []).append(ms)
            if i >= args.warmup:
                cpu.append(cpu_s() - c0)
                for key, a, b in (("render", t0, t1), ("losses", t1, t2), ("backward", t2, t3), ("guard", t3, t3g),
                                  ("adam", t3g, t4), ("step", t0, t4)):
                    parts[key].append(b - a)
                parts["project_bwd"].append(out.timings["project_bwd"] * 1e-3)
        for key, ts in parts.items():
            ks = f"   kernels {statistics.median(kparts[key]) * 1e3:7.1f} ms" if kparts.get(key) else ""
            print(f"  {key:9s} {statistics.median(ts) * 1e3:9.1f} ms{ks}")
        if kernels:
            launches = sum(1 for _ in events)
            print(f"  kernel time: OpenCL events of the {launches} Runtime launches of the last step "
                  f"(pyopencl's fills and copies not counted); slowest kernels, median ms per step:")
            top = sorted(kernels.items(), key=lambda kv: -statistics.median(kv[1]))[:args.top]
            print("    " + ", ".join(f"{name} {statistics.median(ms):.2f}" for name, ms in top))
        print(f"  CPU time per step (all threads) {statistics.median(cpu) * 1e3:.1f} ms "
              f"(/ {os.cpu_count()} cores = {statistics.median(cpu) * 1e3 / (os.cpu_count() or 1):.1f} ms)")
        print(f"seconds per training step: {statistics.median(parts['step']):.3f}; "
              f"load average {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
        steps = []
        for i in range(args.warmup + args.runs):
            rt.queue.finish()
            t0 = time.perf_counter()
            tr.train_step(order[i % len(order)])
            rt.queue.finish()
            if i >= args.warmup:
                steps.append(time.perf_counter() - t0)
        print(f"seconds per Trainer.train_step: {statistics.median(steps):.3f}")
        if tr._between.pairs:
            # an in-between step (half of the default schedule's steps): its target is built on the
            # host (the pair's frames warped to the drawn time, train/between.py), then the same step
            import numpy as np
            rng = np.random.default_rng(0)
            draws, steps = [], []
            for i in range(args.warmup + args.runs):
                t0 = time.perf_counter()
                tr._between.draw(rng)
                t1 = time.perf_counter()
                rt.queue.finish()
                t2 = time.perf_counter()
                tr.train_step_between()
                rt.queue.finish()
                if i >= args.warmup:
                    draws.append(t1 - t0)
                    steps.append(time.perf_counter() - t2)
            print(f"seconds per Trainer.train_step_between: {statistics.median(steps):.3f} "
                  f"(of which the in-between target on the host {statistics.median(draws):.3f})")
            if tr.cfg.between_model > 0:
                # after densify_until the step's forward is read back first and the target blends
                # in the frames moved along the model's motion (between_model): a third read-back
                # and two more warps on the host; with between_model_splat also two renders at the
                # pair's frames, their read-backs and two forward splats
                # (with between_motion_refresh every pair's motion is rendered afresh here, as in
                # the first late step that draws the pair, then timed again while it is kept)
                step0 = tr.step
                kept = [False, True] if tr.cfg.between_model_splat and tr.cfg.between_motion_refresh > 0 else [False]
                for keep in kept:
                    late = []
                    if keep:
                        for index in range(len(tr._between.pairs)):
                            tr._between._pair_motion(index, _motion_renderer(tr), tr.cfg.densify_until)
                    for i in range(args.warmup + args.runs):
                        tr.step = max(step0, tr.cfg.densify_until)
                        if not keep:
                            tr._between._motion.clear()
                        rt.queue.finish()
                        t0 = time.perf_counter()
                        tr.train_step_between()
                        rt.queue.finish()
                        if i >= args.warmup:
                            late.append(time.perf_counter() - t0)
                    tr.step = step0
                    what = ("" if len(kept) == 1 else
                            ", the pair's motion kept" if keep else ", the pair's motion rendered afresh")
                    print(f"seconds per Trainer.train_step_between after densify_until (between_model "
                          f"{tr.cfg.between_model:g}, between_model_splat {tr.cfg.between_model_splat}"
                          f"{what}): {statistics.median(late):.3f}")


def _motion_renderer(tr):
    """(camera, t, t_to) -> the trainer's model's rendered motion [H, W, 2] (Trainer.rendered_motion)."""
    from endowave_cl.render import render
    return lambda camera, t, t_to: tr.rendered_motion(render(tr.rt, tr.params, camera, t, t_to, select=tr.select_live))


if __name__ == "__main__":
    main()
