#!/usr/bin/env python
"""The real training loop's steps, timed per kind, on the default schedule (issue 60).

Runs Trainer.schedule_step, the loop's own choice between a plain step and an in-between step, for
--steps steps in a window before densify_until (--early, a step number) and one after it (--late),
and prints per kind of step the median wall time, kernel time (OpenCL event profiling of the
Runtime's launches, kernel_events.py), host time (wall minus kernels: on a CPU device the kernels
and the host share the cores, so this is the time the device did not run a Runtime kernel), the
Runtime's kernel launches, the blocking reads and the waits for a count copied without blocking (a
binning's pair count, select's live-row count) per step:

    plain           a step on a training frame
    between         an in-between step before densify_until (the static target: flows only)
    between_late    an in-between step after densify_until (the forward read back, the model's
                    motion blended in; the pair's motion at its frames kept, between_motion_refresh)
    between_late+motion   the same where the pair's kept motion was rendered afresh (two more
                    renders and reads; about one late draw in four in a default run)

With between_levels >= 2 every pair's flow prediction at every grid point is built and kept
before the windows (a long run's steady state).  Before the late window every pair's motion is
rendered once with ages spread over between_motion_refresh, so that the window sees refreshes at
about their steady rate.  The Gaussians are the initial ones (or --checkpoint's); the step number
sets the schedule (in-between chance, model blend, learning rates), the Gaussians do not densify.
--full-run trains the whole default pulling
run (`endowave-cl train SCENE --downscale 2`) in a temporary folder and prints its train_seconds;
--blocking-too then trains it again with the loop that waits for every step's outcome.  (The
windows time Trainer.schedule_step, which waits for its step: what the loop's deferred read saves
shows in the full runs only.)

    python benchmarks/bench_train_loop.py [--steps 40] [--early 1000] [--late 4000] [--checkpoint CK.npz]
                                          [--set KEY=VALUE ...] [--both-paths] [--full-run [--blocking-too]]

--both-paths times the in-between targets built on the device (train/between_device.py) and on the
host (OpenCV and numpy), alternated round by round, so that both see the same minutes' load.

The shared EndoNeRF pulling frames are read from ../shared/data (the script says so and stops where
they are absent).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_train_step import SHARED_SCENE  # noqa: E402
from endowave_cl.device import cpu_name  # noqa: E402
from kernel_events import kernel_ms, profile_launches  # noqa: E402

KINDS = ("plain", "between", "between_late", "between_late+motion")


def machine() -> str:
    """'CPU model, N cores' of this host."""
    return f"{cpu_name()}, {os.cpu_count()} cores"


def load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


class ReadCounter:
    """Counts blocking device-to-host reads (pyopencl.enqueue_copy into a numpy array, which every
    cla.Array.get and ops.util.read_back goes through), host-to-device uploads, and waits: the
    binning's pair counts and select's live-row counts (copied without blocking, ops.binning.PairCount)
    read while their copy had not completed, i.e. where the host waited on the device for them, while
    installed."""

    def __init__(self):
        import numpy as np
        import pyopencl as cl
        from endowave_cl.ops.binning import PairCount
        self.reads = self.uploads = self.waits = 0
        plain = cl.enqueue_copy
        plain_value = PairCount.value

        def counted(queue, dest, src, **kw):
            if isinstance(dest, np.ndarray) and kw.get("is_blocking", True):
                self.reads += 1
            elif isinstance(src, np.ndarray):
                self.uploads += 1
            return plain(queue, dest, src, **kw)

        def value(pairs):
            self.waits += int(pairs.pending)
            return plain_value(pairs)
        cl.enqueue_copy = counted
        PairCount.value = value


def time_window(tr, rt, events, counter, start: int, steps: int, warmup: int, rows):
    """Run warmup + steps schedule steps from step number start; append (kind, wall s, kernel s,
    launches, reads, uploads, waits) of each timed step to rows."""
    order = list(tr.scene.train_indices)
    tr.step = start
    for i in range(warmup + steps):
        late = tr.step >= tr.cfg.densify_until
        motion_before = {k: v[0] for k, v in tr._between._motion.items()}
        rt.queue.finish()
        events.clear()
        counter.reads = counter.uploads = counter.waits = 0
        t0 = time.perf_counter()
        kind, _ = tr.schedule_step(order)
        rt.queue.finish()
        wall = time.perf_counter() - t0
        if kind == "between" and late:
            fresh = any(motion_before.get(k) != v[0] for k, v in tr._between._motion.items())
            kind = "between_late+motion" if fresh else "between_late"
        if i >= warmup:
            rows.append((kind, wall, sum(kernel_ms(events).values()) * 1e-3, len(events), counter.reads,
                         counter.uploads, counter.waits))


def spread_motion(tr, at: int):
    """Render every pair's motion (BetweenSampler._pair_motion) with its age spread evenly over
    between_motion_refresh at step at, as a long run's steady state has it."""
    from bench_train_step import _motion_renderer
    b, refresh = tr._between, max(1, tr.cfg.between_motion_refresh)
    if not (tr.cfg.between_model > 0 and tr.cfg.between_model_splat and tr.cfg.between_motion_refresh > 0):
        return
    render = _motion_renderer(tr)
    n = len(b.pairs)
    for index in range(n):
        b._pair_motion(index, render, at - refresh + 1 + (refresh * index) // max(n, 1))


def fill_targets(sampler) -> str:
    """Build and keep every pair's flow prediction at every grid point (between_levels >= 2, host
    targets), as a long run's steady state has them: a default run draws each (pair, grid point)
    about ten times, so nearly every draw finds it kept.  A line saying what was kept."""
    if sampler.levels < 2 or sampler.device is not None:
        return ""
    for index in range(len(sampler.pairs)):
        for j in range(1, sampler.levels):
            sampler.flow_prediction(index, j / float(sampler.levels))
    mib = sum(a.nbytes + b.nbytes for a, b in sampler._static.values()) / 2.0 ** 20
    return f"kept before timing: {len(sampler._static)} in-between targets ({mib:.0f} MiB, between_levels {sampler.levels})"


def report(rows, title: str):
    print(title)
    print(f"  {'kind':21s} {'steps':>5s} {'wall ms':>8s} {'kernel ms':>9s} {'host ms':>8s} {'launches':>8s} "
          f"{'reads':>5s} {'max':>3s} {'uploads':>7s} {'waits':>5s}")
    med = {}
    for kind in KINDS:
        r = [x for x in rows if x[0] == kind]
        if not r:
            continue
        wall = statistics.median(x[1] for x in r) * 1e3
        kern = statistics.median(x[2] for x in r) * 1e3
        host = statistics.median((x[1] - x[2]) for x in r) * 1e3
        med[kind] = wall
        print(f"  {kind:21s} {len(r):5d} {wall:8.1f} {kern:9.1f} {host:8.1f} "
              f"{statistics.median(x[3] for x in r):8.0f} {statistics.median(x[4] for x in r):5.0f} "
              f"{max(x[4] for x in r):3d} {statistics.median(x[5] for x in r):7.0f} "
              f"{statistics.median(x[6] for x in r):5.0f}")
    if "plain" in med:
        print("  ratio to a plain step: " + ", ".join(f"{k} {v / med['plain']:.2f}x" for k, v in med.items()
                                                      if k != "plain"))
    return med


def full_run(scene: Path, downscale: float, sets, blocking: bool = False) -> None:
    """Train the default run in a temporary folder and print its training time (train_seconds:
    the loop without kernel builds, trainer.py) and the final test PSNR.  blocking: with
    $ENDOWAVE_BLOCKING_STEPS=1, the loop that waits for every step's outcome before the next."""
    env = dict(os.environ, ENDOWAVE_BLOCKING_STEPS="1" if blocking else "0")
    with tempfile.TemporaryDirectory() as out:
        cmd = ["endowave-cl", "train", str(scene), "--downscale", f"{downscale:g}", "--out", out]
        for item in sets:
            cmd += ["--set", item]
        loop = "waiting at every step" if blocking else "each step read behind the next"
        print(f"full run ({loop}): {' '.join(cmd)}; load average {load()}")
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, env=env)
        wall = time.perf_counter() - t0
        log = json.loads((Path(out) / "train_log.json").read_text())
        m = log.get("final") or log
        print(f"  train_seconds {m.get('train_seconds', float('nan')):.1f} s (process {wall:.1f} s), "
              f"{m.get('step')} steps, test PSNR {m.get('psnr', float('nan')):.2f} dB; load average {load()}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default=str(SHARED_SCENE))
    ap.add_argument("--downscale", type=float, default=2.0, help="frame size divisor (2: 320x256, the default run)")
    ap.add_argument("--steps", type=int, default=40, help="timed schedule steps per window")
    ap.add_argument("--warmup", type=int, default=5, help="untimed schedule steps before each window")
    ap.add_argument("--early", type=int, default=1000, help="the first window's step number (< densify_until)")
    ap.add_argument("--late", type=int, default=-1,
                    help="the second window's step number (default: halfway from densify_until to the end)")
    ap.add_argument("--rounds", type=int, default=1, help="windows of each kind, alternated early / late")
    ap.add_argument("--checkpoint", help="a trained model's checkpoint (.npz): its Gaussians instead of new ones")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="change a training config key")
    ap.add_argument("--both-paths", action="store_true",
                    help="time the windows with the in-between targets built on the device and on the host "
                         "(the reference path), alternated in each round (by default only where "
                         "train/between.py targets_on_device puts them)")
    ap.add_argument("--full-run", action="store_true", help="also time the whole default run's training")
    ap.add_argument("--blocking-too", action="store_true",
                    help="with --full-run: then the same run with the loop that waits for every step's "
                         "outcome ($ENDOWAVE_BLOCKING_STEPS=1), for the comparison")
    ap.add_argument("--device", default=None)
    args = ap.parse_args(argv)

    scene_path = Path(args.scene)
    if not (scene_path / "poses_bounds.npy").is_file():
        print(f"bench_train_loop: no scene at {scene_path} (the shared EndoNeRF data); nothing timed")
        return 0
    import numpy as np
    from endowave_cl.data.scene import load_scene
    from endowave_cl.runtime import get_runtime
    from endowave_cl.train.config import TrainConfig, with_values
    from endowave_cl.train.trainer import Trainer

    scene = load_scene(scene_path, downscale=args.downscale)
    rt = get_runtime(args.device)
    events = profile_launches(rt)   # before the trainer's first buffer
    counter = ReadCounter()
    cfg = TrainConfig(downscale=args.downscale, eval_every=0, checkpoint_every=0)
    if args.set:
        cfg = with_values(cfg, dict(item.split("=", 1) for item in args.set), "--set", from_text=True)
    with tempfile.TemporaryDirectory() as run:
        tr = Trainer(scene, cfg, run, rt, log=lambda s: None, resume=False)
        if args.checkpoint:
            from endowave_cl.checkpoint import load_checkpoint
            g = load_checkpoint(args.checkpoint)["gaussians"]
            tr.set_gaussians(g, np.full(len(g), -1))   # fresh (zero) Adam moments
        cfg = tr.cfg                                   # resolved for the scene (iterations, density)
        late = args.late if args.late >= 0 else (cfg.densify_until + cfg.iterations) // 2
        if not args.early < cfg.densify_until <= late:
            raise SystemExit(f"bench_train_loop: --early {args.early} must be below densify_until "
                             f"{cfg.densify_until} and --late {late} at or above it")
        print(f"machine: {machine()}; device: {rt.describe()}")
        print(f"scene: {scene_path} ({len(scene.frames)} frames, {len(scene.train_indices)} training, "
              f"{scene.width}x{scene.height}), {len(tr.params['means'])} Gaussians, "
              f"{len(tr._between.pairs)} in-between pairs; schedule {cfg.iterations} steps, densify_until "
              f"{cfg.densify_until}; windows of {args.steps} steps after {args.warmup} at steps {args.early} "
              f"and {late}, {args.rounds} round(s)")
        if args.set:
            print(f"settings: {' '.join(args.set)}")
        print(f"in-between targets built on the {'device' if tr._between.device is not None else 'host'}; "
              f"load average before: {load()}")
        samplers = {("device" if tr._between.device is not None else "host"): tr._between}
        if args.both_paths and tr._between:
            import copy
            other = copy.copy(tr._between)            # the same pairs and caches, the target built the other way
            other._motion = {}
            if tr._between.device is None:
                other.device = other.device_target()
                samplers = {"device": other, "host": tr._between}
            else:
                other.device = None
                samplers["host"] = other
        for sampler in samplers.values():
            kept = fill_targets(sampler)
            if kept:
                print(kept)
        rows = {name: [] for name in samplers}
        for _ in range(args.rounds):
            for name, sampler in samplers.items():     # alternated: each sees the same minutes' load
                tr._between = sampler
                time_window(tr, rt, events, counter, args.early, args.steps, args.warmup, rows[name])
                spread_motion(tr, late)
                time_window(tr, rt, events, counter, late, args.steps, args.warmup, rows[name])
        for name, r in rows.items():
            report(r, f"in-between targets built on the {name}: median per step (kernel: Runtime launches' "
                      f"events; host: wall - kernel; reads: blocking device-to-host reads, max: the most in one "
                      f"step; waits: pair or live-row counts the host waited for; load average after: "
                      f"{load()})")
    if args.full_run:
        full_run(scene_path, args.downscale, args.set)
        if args.blocking_too:
            full_run(scene_path, args.downscale, args.set, blocking=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
