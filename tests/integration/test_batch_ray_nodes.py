"""`endowave-cl batch` on a Ray cluster of two nodes on this machine (issue 58): ``ray start --head``
(1 CPU, custom resource ``node_a``) plus ``ray start --address`` (1 CPU, ``node_b``), both in their
own temporary folder and with their own HOME (so no ~/.ray of this machine is read).  Two tiny
scenes train at once: the executor spreads them, one on each node.  Once the task on the second
node has written a checkpoint the whole second node is SIGKILLed (its raylet and every process under
it); Ray re-runs the task on the head node, where it resumes from that checkpoint.

Skips when Ray is not installed or a node cannot start; everything started here is killed by pid at
the end.  About a minute on 2 busy cores (two `ray start`s, two short trainings, a retry)."""
from __future__ import annotations

import io
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

ITERATIONS = 150

MANIFEST = f"""
root = "{{root}}"
stages = ["train"]
scenes = ["data/s*"]

[resources]
cpus = 1
retries = 2

[settings]
iterations = {ITERATIONS}
init_points = 500
eval_every = 0
log_every = 5
checkpoint_every = 20
use_flow = false
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _procs():
    """{pid: (ppid, cmdline)} of this machine's processes (Linux /proc)."""
    out = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            with open(f"/proc/{d}/cmdline", "rb") as f:
                cmd = f.read().replace(b"\0", b" ").decode(errors="replace")
        except (OSError, ValueError, IndexError):
            continue
        out[int(d)] = (ppid, cmd)
    return out


def _with_descendants(roots, procs=None):
    procs = _procs() if procs is None else procs
    found, todo = set(), list(roots)
    while todo:
        p = todo.pop()
        if p in found:
            continue
        found.add(p)
        todo += [c for c, (pp, _) in procs.items() if pp == p]
    return found


def _kill(pids):
    for p in pids:
        try:
            os.kill(p, signal.SIGKILL)
        except OSError:
            pass


def _cluster_pids(temp: str):
    """Every process of the cluster started in ``temp``: those naming the folder, and under them."""
    procs = _procs()
    return _with_descendants([p for p, (_, cmd) in procs.items() if temp in cmd and p != os.getpid()], procs)


@pytest.fixture()
def two_nodes(tmp_path, monkeypatch):
    ray = pytest.importorskip("ray")
    if ray.is_initialized():
        pytest.skip("this process is already connected to a Ray instance")
    if not os.path.isdir("/proc"):
        pytest.skip("needs Linux /proc to find the nodes' processes")
    ray_cli = Path(sys.executable).with_name("ray")
    if not ray_cli.is_file():
        pytest.skip(f"no `ray` command beside {sys.executable}")
    home = tmp_path / "home"
    home.mkdir()
    temp = tempfile.mkdtemp(prefix="ewray-", dir="/tmp")     # short: Ray's socket paths live under it
    cache = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    env = {"HOME": str(home), "XDG_CACHE_HOME": cache,     # the kernel caches stay warm
           "RAY_USAGE_STATS_ENABLED": "0"}
    for k, v in env.items():
        monkeypatch.setenv(k, v)                            # the driver (this process) too
    port = _free_port()
    address = f"127.0.0.1:{port}"

    def start(args, what):
        try:
            r = subprocess.run([str(ray_cli), "start", *args], env=dict(os.environ), capture_output=True,
                               text=True, timeout=240)
        except subprocess.TimeoutExpired:
            r = None
        if r is None or r.returncode != 0:
            _kill(_cluster_pids(temp))
            shutil.rmtree(temp, ignore_errors=True)
            lines = [ln for ln in ((r.stderr + r.stdout) if r else "timed out").strip().splitlines() if ln.strip()]
            pytest.skip(f"Ray cannot start {what} here: {lines[-1] if lines else r.returncode}")

    start(["--head", f"--port={port}", "--num-cpus=1", '--resources={"node_a": 1}', "--include-dashboard=false",
           "--disable-usage-stats", f"--temp-dir={temp}"], "a head node")
    start([f"--address={address}", "--num-cpus=1", '--resources={"node_b": 1}'], "a second node")
    try:
        yield ray, address, temp
    finally:
        if ray.is_initialized():
            ray.shutdown()
        _kill(_cluster_pids(temp))
        shutil.rmtree(temp, ignore_errors=True)


class NodeKiller(threading.Thread):
    """SIGKILLs the whole node ``node_id`` (its raylet and every process under it) once a run folder
    under ``root`` holds a checkpoint and is locked by a process of that node."""

    def __init__(self, root: Path, node_id: str, timeout: float = 900.0):
        super().__init__(daemon=True)
        self.root, self.node_id, self.timeout = root, node_id, timeout
        self.scene = self.step = self.pid = None
        self.done = threading.Event()

    def run(self):
        end = time.monotonic() + self.timeout
        while time.monotonic() < end and not self.done.is_set():
            procs = _procs()
            raylet = [p for p, (_, cmd) in procs.items() if f"--node_id={self.node_id}" in cmd and "raylet" in cmd]
            node = _with_descendants(raylet, procs) if raylet else set()
            for run in sorted(self.root.glob("s*")):
                cks = list(run.glob("checkpoint_*.npz"))
                try:
                    pid = int((run / ".lock").read_text().strip())
                except (OSError, ValueError):
                    continue
                if cks and pid in node:
                    _kill(node)
                    self.scene, self.pid = run.name, pid
                    self.step = max(int(p.name[11:18]) for p in cks)
                    return
            time.sleep(0.05)


def test_tasks_spread_over_two_nodes_and_a_killed_nodes_task_is_retried(two_nodes, tmp_path):
    from endowave_cl.batch.executors import RayExecutor
    from endowave_cl.batch.manifest import load_manifest
    from endowave_cl.batch.runner import run_batch
    from endowave_cl.data.synth import make_synthetic_scene
    ray, address, _ = two_nodes
    for i in range(2):
        make_synthetic_scene(tmp_path / "data" / f"s{i}", width=48, height=32, frames=8, seed=i)
    (tmp_path / "m.toml").write_text(MANIFEST.format(root="out"))
    m = load_manifest(tmp_path / "m.toml")

    ex = RayExecutor(address, None, m.resources)
    try:
        assert "2 node(s)" in ex.describe()
        nodes = {n["NodeID"]: n for n in ray.nodes() if n["Alive"]}
        head = next(i for i, n in nodes.items() if "node_a" in n["Resources"])
        second = next(i for i, n in nodes.items() if "node_b" in n["Resources"])
        killer = NodeKiller(m.root, second)
        killer.start()
        out = io.StringIO()
        res = run_batch(m, ex, out=out, interval=1.0)
        killer.done.set()
        killer.join(timeout=5)
    finally:
        ex.shutdown()
    text = out.getvalue()
    assert killer.scene is not None, f"no task on the second node was seen training with a checkpoint\n{text}"
    results = {t.scene: t.result for t in res.tasks.values() if t.stage == "train"}
    assert sorted(results) == ["s0", "s1"] and all(r and r["ok"] for r in results.values()), (results, text)

    # both nodes ran a task: the killed one began on the second node (the killer checked its pid),
    # the other ran on the head node, at the same time
    other = next(s for s in results if s != killer.scene)
    assert results[other]["node"] == head and results[other]["attempt"] == 1, results[other]

    # the killed node's task was retried by Ray on the node left, and resumed from its checkpoint
    r = results[killer.scene]
    assert r["attempt"] == 2 and r["node"] == head and r["pid"] != killer.pid, r
    run = m.root / killer.scene
    from endowave_cl.batch import tasks as T
    log = (T.batch_dir(run) / "train.log").read_text()
    assert f"attempt 1, pid {killer.pid}" in log and "attempt 2" in log, log
    resumed_at = int(log.split(f"resuming from {run}/checkpoint_")[1][:7])
    assert resumed_at >= killer.step > 0
    steps = [h["step"] for h in json.loads((run / "train_log.json").read_text())["history"]]
    assert steps == sorted(set(steps)) and steps[-1] == ITERATIONS
    rep = json.loads((m.root / "report.json").read_text())
    assert rep["counts"] == {"done": 2, "failed": 0, "incomplete": 0}
