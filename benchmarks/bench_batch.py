"""Wall time of a batch of synthetic scenes through `endowave-cl batch` (Ray, and the process pool)
against running the same commands one after another, plus Ray's own overhead per task.

  python benchmarks/bench_batch.py [--scenes 4] [--size 96x64] [--frames 16] [--iterations 300]

Sequential: for each scene `endowave-cl flow`, `train`, `eval` as separate processes, each using
every core (PoCL's default).  Batch: the same stages as tasks of 1 CPU each on a local Ray
instance of `os.cpu_count()` CPUs (2 tasks at once on 2 cores), then on the process pool.
Prints `uptime` before and after: the figures only compare on an otherwise idle machine.
"""
from __future__ import annotations

import argparse
import io
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def sh(*args):
    subprocess.run([sys.executable, "-m", "endowave_cl", *args], check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--size", default="96x64")
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--skip-pool", action="store_true")
    a = ap.parse_args()
    w, h = map(int, a.size.split("x"))
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs; "
          f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    from endowave_cl.data.synth import make_synthetic_scene
    base = Path(tempfile.mkdtemp(prefix="bench-batch-"))
    names = [f"s{i}" for i in range(a.scenes)]
    for i, n in enumerate(names):
        make_synthetic_scene(base / "data" / n, width=w, height=h, frames=a.frames, seed=i)
    sets = {"iterations": a.iterations, "init_points": 2000, "eval_every": 0}
    print("uptime before:", subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())
    # a warm program cache for everyone: compile the kernels once before timing
    sh("train", str(base / "data" / names[0]), "--out", str(base / "warm"), "--set", "iterations=2",
       "--set", "init_points=200", "--quiet")

    t = time.perf_counter()
    for n in names:
        run = base / "seq" / n
        sh("flow", str(base / "data" / n), "--no-progress")
        sh("train", str(base / "data" / n), "--out", str(run), "--quiet", *[x for k, v in sets.items()
                                                                         for x in ("--set", f"{k}={v}")])
        sh("eval", str(run), "--fps-runs", "0")
    seq = time.perf_counter() - t
    print(f"one after another: {seq:.1f} s")

    settings = "\n".join(f"{k} = {v}" for k, v in sets.items())
    import ray
    from endowave_cl.batch.executors import PoolExecutor, RayExecutor
    from endowave_cl.batch.manifest import load_manifest
    from endowave_cl.batch.runner import run_batch
    results = {}
    for mode in ["ray"] + ([] if a.skip_pool else ["pool"]):
        mf = base / f"{mode}.toml"
        mf.write_text(f'root = "out-{mode}"\nstages = ["flow", "train", "eval"]\nscenes = ["data/s*"]\n'
                      f'[resources]\ncpus = 1\n[settings]\n{settings}\n[eval]\nfps_runs = 0\n')
        m = load_manifest(mf)
        t = time.perf_counter()
        if mode == "ray":
            t_init = time.perf_counter()
            ex = RayExecutor(None, os.cpu_count(), m.resources)
            init = time.perf_counter() - t_init
        else:
            ex, init = PoolExecutor(os.cpu_count() or 1, m.resources), 0.0
        res = run_batch(m, ex, out=io.StringIO(), interval=1e9)
        wall = time.perf_counter() - t
        inside = sum(tk.result["seconds"] for tk in res.tasks.values() if tk.result)
        dispatch = [tk.result["started"] - tk.started for tk in res.tasks.values() if tk.result]
        back = [tk.ended - (tk.result["started"] + tk.result["seconds"]) for tk in res.tasks.values() if tk.result]
        results[mode] = wall
        print(f"{mode}: {wall:.1f} s wall ({init:.1f} s of it starting Ray), {len(res.ran)} tasks, "
              f"{inside:.1f} s inside tasks; submit-to-start median {statistics.median(dispatch):.2f} s "
              f"(max {max(dispatch):.2f} s, includes waiting for a free CPU), result-return median "
              f"{1e3 * statistics.median(back):.0f} ms; failed: {res.failed_scenes}")
    # Ray's own overhead: empty tasks on the same kind of local instance
    ray.init(num_cpus=os.cpu_count(), include_dashboard=False, log_to_driver=False)

    @ray.remote(num_cpus=1)
    def noop():
        return 0
    ray.get([noop.remote() for _ in range(4)])          # start the workers
    t = time.perf_counter()
    for _ in range(200):
        ray.get(noop.remote())
    rt = (time.perf_counter() - t) / 200
    t = time.perf_counter()
    ray.get([noop.remote() for _ in range(1000)])
    thr = 1000 / (time.perf_counter() - t)
    ray.shutdown()
    print(f"ray empty task: {1e3 * rt:.1f} ms round trip, {thr:.0f} tasks/s in parallel")
    print("speed-up vs one after another: " + ", ".join(f"{k} {seq / v:.2f}x" for k, v in results.items()))
    print("uptime after:", subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())


if __name__ == "__main__":
    main()
