"""Run a manifest of scenes through flow / train / eval / render / export, locally or on a Ray cluster.

Examples:
  endowave-cl batch dataset.toml                          # local Ray, or a process pool without Ray
  endowave-cl batch dataset.toml --address ray://head:10001   # an existing Ray cluster (or $RAY_ADDRESS)
  endowave-cl batch dataset.toml --force                  # redo every stage of every scene
One task per scene and stage, each writing only its run folder ROOT/<scene>; a task whose worker
dies is retried and resumes from its newest checkpoint; a scene that fails is reported and the rest
go on; a re-run skips what is complete.  Writes ROOT/report.md, report.json and report.csv.
The manifest format and running on a cluster: docs/BATCH.md.  Exit status 1 when a scene failed.
"""
from __future__ import annotations

import math

from ..batch.executors import make_executor
from ..batch.manifest import load_manifest, remote_address
from ..batch.runner import run_batch
from ..errors import EndowaveError


def add_arguments(p) -> None:
    p.add_argument("manifest", help="TOML manifest (docs/BATCH.md)")
    p.add_argument("--address", help="Ray cluster, e.g. ray://HOST:10001 (default: $RAY_ADDRESS, else local)")
    p.add_argument("--executor", choices=("auto", "ray", "pool"), default="auto",
                   help="auto: Ray when installed, else a local process pool (default auto)")
    p.add_argument("--cpus", type=int, help="CPU cores to use on this machine (local Ray or the pool; "
                                            "default: all)")
    p.add_argument("--gpus", type=int, help="GPUs on this machine for the process pool (default 1 when the "
                                            "manifest asks for GPUs)")
    p.add_argument("--force", action="store_true", help="redo every stage, complete or not (training "
                                                        "starts over; the earlier run moves to RUN/previous_run/)")
    p.add_argument("--retry-failed", action="store_true",
                   help="run again the stages that failed with a data error on unchanged inputs")
    p.add_argument("--interval", type=float, default=10.0, help="seconds between progress lines (default 10)")


def run(args) -> int:
    if args.cpus is not None and args.cpus < 1:
        raise EndowaveError(f"--cpus must be at least 1, got {args.cpus}")
    if args.gpus is not None and args.gpus < 0:
        raise EndowaveError(f"--gpus must be >= 0, got {args.gpus}")
    if not (math.isfinite(args.interval) and args.interval > 0):
        raise EndowaveError(f"--interval must be > 0, got {args.interval}")
    m = load_manifest(args.manifest)
    ex = make_executor(args.executor, remote_address(args.address), m.resources, args.cpus, args.gpus)
    res = run_batch(m, ex, force=args.force, retry_failed=args.retry_failed, interval=args.interval)
    rep = res.report
    print(f"report: {m.root / 'report.md'} (and .json, .csv): {rep['counts']['done']} done, "
          f"{rep['counts']['failed']} failed, {rep['counts']['incomplete']} incomplete; {res.seconds:.0f} s")
    return 1 if rep["counts"]["failed"] or rep["counts"]["incomplete"] else 0
