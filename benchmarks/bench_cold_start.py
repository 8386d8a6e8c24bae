#!/usr/bin/env python
"""What a cold start costs: wall time of a whole short render benchmark process with empty and with
filled caches.

Each measurement runs ``benchmarks/bench_render.py --n N --runs 1 --warmup 0 --no-reference`` of --repo
(tools/bench_render.py in a checkout from before benchmarks/) in a fresh process (imports, device,
kernel builds or cache loads, one forward and backward frame):
  cold         an empty endowave-cl cache ($ENDOWAVE_CL_CACHE: no programs, no probe verdicts),
               the driver's own cache (PoCL: POCL_CACHE_DIR) empty too;
  cold-ours    only the endowave-cl cache empty (the driver's cache filled);
  warm         both filled.
Run it for this tree and for an older one (--repo) to see what the rasterizer probe adds.

    python benchmarks/bench_cold_start.py [--repo .] [--n 20000] [--repeat 3]
"""
from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time


def run_once(repo: str, n: int, ours: str, driver: str) -> float:
    env = dict(os.environ, ENDOWAVE_CL_CACHE=ours, POCL_CACHE_DIR=driver, PYTHONPATH=repo)
    for k in ("ENDOWAVE_RASTER_VARIANT", "ENDOWAVE_RASTER_VW", "ENDOWAVE_CL_NO_DISK_CACHE"):
        env.pop(k, None)
    script = os.path.join(repo, "benchmarks", "bench_render.py")
    if not os.path.isfile(script):     # a checkout from before benchmarks/ (issue 59) kept it in tools/
        script = os.path.join(repo, "tools", "bench_render.py")
    cmd = [sys.executable, script, "--n", str(n), "--runs", "1",
           "--warmup", "0", "--no-reference"]
    t0 = time.perf_counter()
    subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main() -> int:
    here = os.path.dirname(os.path.abspath(__file__))
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repo", default=os.path.dirname(here), help="source tree to run (default: this one)")
    ap.add_argument("--n", type=int, default=20000)
    ap.add_argument("--repeat", type=int, default=3, help="measurements per condition (median)")
    a = ap.parse_args()
    repo = os.path.abspath(a.repo)
    times = {"cold": [], "cold-ours": [], "warm": []}
    for _ in range(a.repeat):
        ours, driver = tempfile.mkdtemp(prefix="ew-ours-"), tempfile.mkdtemp(prefix="ew-pocl-")
        try:
            times["cold"].append(run_once(repo, a.n, ours, driver))
            shutil.rmtree(ours)
            os.mkdir(ours)
            times["cold-ours"].append(run_once(repo, a.n, ours, driver))
            times["warm"].append(run_once(repo, a.n, ours, driver))
        finally:
            shutil.rmtree(ours, ignore_errors=True)
            shutil.rmtree(driver, ignore_errors=True)
    print(f"repo {repo}, N={a.n}, load average {os.getloadavg()[0]:.1f}, {os.cpu_count()} cores")
    for k, v in times.items():
        print(f"{k:10s} median {statistics.median(v):6.1f} s   ({', '.join(f'{x:.1f}' for x in v)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
