"""Where batch tasks run.  Both executors have the same small interface for the runner:

  submit(key, spec)       queue a task (spec from tasks.make_spec)
  poll(timeout) -> list   [(key, result)] of tasks that ended (result as tasks.run_task returns it)
  shutdown()

and the same failure rule: a task whose worker process dies (SIGKILL, the OOM killer, a lost node)
is run again, up to ``retries`` more times; the retry resumes from what the dead attempt left (train
resumes from its newest checkpoint).  A task that *fails* (the command reports an error) is not
retried: the runner reports it.

* ``RayExecutor``: one Ray task per (scene, stage), scheduled by Ray on the CPU / GPU resources the
  manifest asks for and spread over the cluster's nodes (Ray's SPREAD strategy: Ray's default packs
  tasks onto the driver's node until half of it is busy, while a training task keeps a whole
  OpenCL device busy whatever CPUs it asks for); Ray's own ``max_retries`` re-runs tasks whose
  worker or node died.  The task runs in-process in the Ray worker (``tasks.run_task``), so a
  killed worker is a killed training; its result names the Ray node that ran it (``node``).
* ``PoolExecutor``: a plain process pool without Ray: at most ``workers`` child processes
  (``python -m endowave_cl.batch.tasks``), one per task, re-launched when killed by a signal.
"""
from __future__ import annotations

import importlib.util
import json
import logging
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Dict, List, Optional, Tuple

from ..errors import EndowaveError
from .tasks import RESULT_PREFIX, run_task


def ray_available() -> bool:
    return importlib.util.find_spec("ray") is not None


def _package_parent() -> str:
    """The folder holding the endowave_cl package: local Ray workers get it on PYTHONPATH, so a
    source checkout that is not pip-installed works too."""
    return str(Path(__file__).resolve().parents[2])


def _run_task_on_ray_node(spec: dict) -> dict:
    """tasks.run_task in a Ray worker; the result also names the Ray node (its id) that ran it."""
    res = run_task(spec)
    try:
        import ray
        res["node"] = ray.get_runtime_context().get_node_id()
    except Exception:  # noqa: BLE001  the node is for the record only
        pass
    return res


def _failed(key, kind: str, error: str) -> dict:
    scene, stage = key
    return {"ok": False, "kind": kind, "error": error, "scene": scene, "stage": stage}


class RayExecutor:
    name = "ray"

    def __init__(self, address: Optional[str], cpus: Optional[int], resources: dict):
        import ray
        self.ray = ray
        self.resources = resources
        self.started_here = False
        if not ray.is_initialized():
            kw = dict(include_dashboard=False, log_to_driver=False, logging_level=logging.WARNING)
            try:
                if address:
                    ray.init(address=address, **kw)
                else:
                    ray.init(num_cpus=cpus or os.cpu_count() or 1, **kw)
            except Exception as e:  # noqa: BLE001  ConnectionError, RuntimeError, ValueError, ...: one line
                where = f"the Ray cluster at {address}" if address else "a local Ray instance"
                first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
                raise EndowaveError(f"cannot start or reach {where}: {first}") from None
            self.started_here = True
        self.local = not address      # workers on this machine: give them this package's path
        self._remote = ray.remote(_run_task_on_ray_node)
        self._refs: Dict[object, Tuple[str, str]] = {}

    def describe(self) -> str:
        r = self.ray.cluster_resources()
        return (f"Ray ({len(self.ray.nodes())} node(s), {r.get('CPU', 0):g} CPUs, {r.get('GPU', 0):g} GPUs)")

    def capacity_check(self) -> None:
        """A task asking for more than the whole cluster has would wait forever: say so now."""
        r = self.ray.cluster_resources()
        for name, want in (("CPU", self.resources["cpus"]), ("GPU", self.resources["gpus"])):
            if want > r.get(name, 0):
                raise EndowaveError(f"each task asks for {want:g} {name}(s) (manifest [resources]) but the Ray "
                                    f"cluster has {r.get(name, 0):g}")

    def submit(self, key, spec: dict) -> None:
        env = dict(spec["env"])
        if self.local:
            env["PYTHONPATH"] = os.pathsep.join(p for p in (_package_parent(), os.environ.get("PYTHONPATH")) if p)
        ref = self._remote.options(
            num_cpus=self.resources["cpus"], num_gpus=self.resources["gpus"],
            max_retries=self.resources["retries"], retry_exceptions=False, scheduling_strategy="SPREAD",
            runtime_env={"env_vars": env}, name=f"endowave {spec['stage']} {spec['scene']}").remote(spec)
        self._refs[ref] = key

    def poll(self, timeout: float) -> List[Tuple[tuple, dict]]:
        if not self._refs:
            time.sleep(timeout)
            return []
        ray = self.ray
        refs = list(self._refs)
        ready, rest = ray.wait(refs, num_returns=1, timeout=timeout)
        if ready and rest:
            ready += ray.wait(rest, num_returns=len(rest), timeout=0)[0]
        out = []
        for ref in ready:
            key = self._refs.pop(ref)
            try:
                out.append((key, ray.get(ref)))
            except ray.exceptions.RayTaskError as e:
                # run_task raised (it returns failures as results: this is a bug or a setup problem
                # on the node, e.g. the output root not writable there): not retried by Ray
                cause = getattr(e, "cause", None) or e
                first = (str(cause).strip().splitlines() or [""])[0]
                out.append((key, _failed(key, "unexpected", f"the task raised {type(cause).__name__}: {first[:300]}")))
            except ray.exceptions.RayError as e:
                # the worker (or its node) died more often than the retries allow, or the task
                # could not start (e.g. endowave-cl not installed on the cluster's nodes)
                lines = [ln for ln in str(e).strip().splitlines() if ln.strip()]
                why = type(e).__name__ + (f": {lines[-1].strip()}" if lines else "")
                out.append((key, _failed(key, "worker", f"the task's Ray worker failed after "
                                                        f"{self.resources['retries']} retries ({why[:300]})")))
        return out

    def shutdown(self) -> None:
        for ref in list(self._refs):
            try:
                self.ray.cancel(ref, force=True)
            except Exception:  # noqa: BLE001  best effort on the way out
                pass
        self._refs.clear()
        if self.started_here:
            self.started_here = False
            self.ray.shutdown()


class _Child:
    def __init__(self, key, spec, proc, slot, attempt):
        self.key, self.spec, self.proc, self.slot, self.attempt = key, spec, proc, slot, attempt
        self.output: List[str] = []
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self):
        for line in self.proc.stdout:
            self.output.append(line)
            del self.output[:-50]            # only the tail is ever looked at


class PoolExecutor:
    name = "process pool"

    def __init__(self, workers: int, resources: dict, gpus: Optional[int] = None):
        self.resources = resources
        g = resources["gpus"]
        if g > 0:
            total = gpus if gpus is not None else 1      # without --gpus: one GPU, shared
            if g > total:
                raise EndowaveError(f"each task asks for {g:g} GPU(s) (manifest [resources]) but --gpus is {total}")
            workers = min(workers, int(total // g))     # e.g. 0.5 GPU per task on 1 GPU: 2 at once
        self.workers = max(1, workers)
        self.gpus_per_task = int(g) if g >= 1 and float(g).is_integer() else 0
        self.queue: List[Tuple[tuple, dict, int]] = []
        self.children: List[_Child] = []
        self.free_slots = list(range(self.workers))

    def describe(self) -> str:
        return f"a process pool of {self.workers} worker(s)"

    def capacity_check(self) -> None:
        pass

    def submit(self, key, spec: dict) -> None:
        self.queue.append((key, spec, 1))

    def _start(self, key, spec, attempt) -> None:
        slot = self.free_slots.pop(0)
        env = dict(os.environ)
        env.update(spec["env"])
        env["PYTHONPATH"] = os.pathsep.join(p for p in (_package_parent(), os.environ.get("PYTHONPATH")) if p)
        if self.gpus_per_task:     # whole GPUs: each slot its own (NVIDIA OpenCL follows CUDA_VISIBLE_DEVICES)
            ids = range(slot * self.gpus_per_task, (slot + 1) * self.gpus_per_task)
            env["CUDA_VISIBLE_DEVICES"] = ",".join(map(str, ids))
        proc = subprocess.Popen([sys.executable, "-m", "endowave_cl.batch.tasks"], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env, text=True)
        proc.stdin.write(json.dumps(spec))
        proc.stdin.close()
        self.children.append(_Child(key, spec, proc, slot, attempt))

    def poll(self, timeout: float) -> List[Tuple[tuple, dict]]:
        deadline = time.monotonic() + timeout
        out = []
        while True:
            while self.queue and self.free_slots:
                self._start(*self.queue.pop(0))
            for c in list(self.children):
                rc = c.proc.poll()
                if rc is None:
                    continue
                c.reader.join(timeout=5)
                self.children.remove(c)
                self.free_slots.append(c.slot)
                result = next((json.loads(ln[len(RESULT_PREFIX):]) for ln in reversed(c.output)
                               if ln.startswith(RESULT_PREFIX)), None)
                if result is not None:
                    out.append((c.key, result))
                elif rc < 0 and c.attempt <= self.resources["retries"]:
                    # killed by a signal: run it again (first in line); the retry resumes
                    self.queue.insert(0, (c.key, c.spec, c.attempt + 1))
                elif rc < 0:
                    out.append((c.key, _failed(c.key, "worker", f"the task's worker process was killed by signal "
                                                                f"{-rc} {c.attempt} time(s); no retries left")))
                else:
                    tail = "".join(c.output[-3:]).strip().splitlines()
                    out.append((c.key, _failed(c.key, "unexpected", f"the task's worker process exited with status "
                                                                    f"{rc}: {tail[-1] if tail else 'no output'}")))
            if out or time.monotonic() >= deadline or (not self.children and not self.queue):
                return out
            time.sleep(min(0.05, max(0.0, deadline - time.monotonic())))

    def shutdown(self) -> None:
        """Children get SIGTERM (train saves a checkpoint and stops), then SIGKILL after a while."""
        self.queue.clear()
        for c in self.children:
            if c.proc.poll() is None:
                c.proc.terminate()
        end = time.monotonic() + 30
        for c in self.children:
            try:
                c.proc.wait(timeout=max(0.1, end - time.monotonic()))
            except subprocess.TimeoutExpired:
                c.proc.kill()
        self.children.clear()


def make_executor(kind: str, address: Optional[str], resources: dict, cpus: Optional[int] = None,
                  gpus: Optional[int] = None, log=print):
    """kind: "auto" (Ray when installed, else the pool), "ray" or "pool"."""
    if kind not in ("auto", "ray", "pool"):
        raise EndowaveError(f"--executor must be auto, ray or pool, got {kind!r}")
    if kind == "pool" and address:
        raise EndowaveError("--executor pool runs on this machine; it cannot use --address / RAY_ADDRESS")
    if kind != "pool" and ray_available():
        return RayExecutor(address, cpus, resources)
    if kind == "ray" or address:
        raise EndowaveError("Ray is not installed: pip install 'endowave-cl[cluster]' "
                            "(or leave out --address / RAY_ADDRESS to use a local process pool)")
    n = cpus or os.cpu_count() or 1
    if kind == "auto":
        log("Ray is not installed: running on a local process pool (pip install 'endowave-cl[cluster]' for Ray)")
    return PoolExecutor(max(1, int(n // resources["cpus"])), resources, gpus)
