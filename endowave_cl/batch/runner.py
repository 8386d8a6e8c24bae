"""The batch scheduler: plan every (scene, stage) from the run folders' files, submit the tasks
whose stage before them is complete, print progress, write the report.

Stage order within a scene: flow -> train -> {eval, render, export} (the last three in parallel).
A stage that will run makes the stages after it run too (a new model needs a new evaluation); a
stage that fails leaves the scene's later stages not run, and the other scenes go on.
"""
from __future__ import annotations

import re
import sys
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, TextIO, Tuple

from .manifest import Manifest
from .report import write_report
from . import tasks as T

AFTER = {"flow": None, "train": "flow", "eval": "train", "render": "train", "export": "train"}
DEFAULT_INTERVAL = 10.0          # seconds between progress blocks (one line per running scene)

_TRAIN_LINE = re.compile(r"^train: (?P<step>\d+)/(?P<total>\d+) it \((?P<pct>\d+)%\)(?P<rest>.*)$")
_LEFT = re.compile(r", (\S+) left")
_PSNR = re.compile(r"psnr=([-\d.]+)")


@dataclass
class Task:
    scene: str
    stage: str
    state: str                   # done (complete before), todo, failed (recorded), running, ok, error, skipped
    why: str = ""
    restart: bool = False
    result: Optional[dict] = None
    started: Optional[float] = None       # when it was submitted (driver clock)
    ended: Optional[float] = None         # when its result arrived


@dataclass
class BatchResult:
    tasks: Dict[Tuple[str, str], Task]
    ran: List[Tuple[str, str]] = field(default_factory=list)      # tasks executed by this invocation
    report: Optional[dict] = None
    seconds: float = 0.0

    @property
    def failed_scenes(self) -> List[str]:
        return sorted({t.scene for t in self.tasks.values() if t.state in ("error", "failed")})


def _fmt_time(s: float) -> str:
    s = int(round(max(0.0, s)))
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else (f"{s // 60}m{s % 60:02d}s" if s >= 60 else f"{s}s")


def train_progress(run_dir) -> Optional[dict]:
    """The newest plain progress line of a running training (RUN/batch/train.log), parsed:
    {"step", "total", "pct", "eta", "psnr"}; None before the first one."""
    path = T.batch_dir(run_dir) / "train.log"
    try:
        with open(path, "rb") as f:
            f.seek(0, 2)
            f.seek(max(0, f.tell() - 4096))
            lines = f.read().decode("utf-8", "replace").splitlines()
    except OSError:
        return None
    for ln in reversed(lines):
        if ln.startswith("== batch"):
            return None                  # a new attempt that has not printed progress yet
        m = _TRAIN_LINE.match(ln.strip())
        if m:
            eta = _LEFT.search(m["rest"])
            psnr = _PSNR.search(m["rest"])
            return {"step": int(m["step"]), "total": int(m["total"]), "pct": int(m["pct"]),
                    "eta": eta.group(1) if eta else None, "psnr": float(psnr.group(1)) if psnr else None}
    return None


class Runner:
    def __init__(self, manifest: Manifest, executor, force: bool = False, retry_failed: bool = False,
                 out: TextIO = None, interval: float = DEFAULT_INTERVAL):
        self.m = manifest
        self.ex = executor
        self.force, self.retry_failed = force, retry_failed
        self.out = out if out is not None else sys.stdout
        self.interval = interval
        self.batch_id = uuid.uuid4().hex[:12]
        self.tasks: Dict[Tuple[str, str], Task] = {}
        self.scenes = {s.name: s for s in manifest.scenes}

    def say(self, text: str) -> None:
        self.out.write(text + "\n")
        self.out.flush()

    def run_dir(self, name: str) -> Path:
        return self.m.root / name

    def signature(self, scene, stage: str) -> str:
        opts = {"stage": stage, "options": T.stage_options(self.m, scene, stage)}
        if stage not in ("flow", "train"):
            opts["model"] = T.model_token(self.run_dir(scene.name))
        return T.scene_signature(scene.path, opts)

    # ------------------------------------------------------------------ plan
    def plan(self) -> None:
        for scene in self.m.scenes:
            rd = self.run_dir(scene.name)
            todo_before = set()
            for stage in self.m.stages:
                dep = AFTER[stage]
                if dep in todo_before:
                    # the stage before runs now (a new flow cache does not change a model; a new
                    # model does need every later stage again)
                    t = Task(scene.name, stage, "todo", f"after {dep}")
                    if dep == "flow":
                        st, why, restart = T.stage_status(self.m, scene, stage, rd, self.force, self.retry_failed,
                                                          self.signature(scene, stage))
                        t = Task(scene.name, stage, "todo" if st != "done" else "done", why, restart)
                else:
                    st, why, restart = T.stage_status(self.m, scene, stage, rd, self.force, self.retry_failed,
                                                      self.signature(scene, stage))
                    t = Task(scene.name, stage, st, why, restart)
                if t.state == "todo":
                    todo_before.add(stage)
                elif t.state == "failed":
                    todo_before.add(stage)          # later stages: not run (see _blocked)
                self.tasks[(scene.name, stage)] = t

    def _blocked(self, t: Task) -> Optional[str]:
        """Why a waiting task cannot run (a stage before it failed), "" if it must wait, None if ready."""
        dep = AFTER[t.stage]
        while dep is not None and (t.scene, dep) not in self.tasks:
            dep = AFTER[dep]                 # a stage not in the manifest: look further back
        if dep is None:
            return None
        d = self.tasks[(t.scene, dep)]
        if d.state in ("error", "failed", "skipped"):
            return f"not run: {dep} failed"
        if d.state in ("done", "ok"):
            return None
        return ""

    # ------------------------------------------------------------------ run
    def _mark_blocked(self) -> None:
        """Tasks after a failed stage will not run: mark them (in stage order, so it propagates)."""
        for key, t in self.tasks.items():
            if t.state == "todo":
                why = self._blocked(t)
                if why:
                    t.state, t.why = "skipped", why

    def _started(self, t: Task) -> bool:
        """Whether a submitted task has begun (its attempt record names this batch), rather than
        waiting for a free worker or for resources."""
        rec = T.read_json(T.record(self.run_dir(t.scene), t.stage, ".attempt"))
        return isinstance(rec, dict) and rec.get("batch_id") == self.batch_id

    def _submit_ready(self) -> None:
        self._mark_blocked()
        for key, t in self.tasks.items():
            if t.state != "todo":
                continue
            why = self._blocked(t)
            if why is None:
                scene = self.scenes[t.scene]
                spec = T.make_spec(self.m, scene, t.stage, self.run_dir(t.scene), self.batch_id, t.restart,
                                   self.signature(scene, t.stage))
                t.state, t.started = "running", time.time()
                self.ex.submit(key, spec)
            elif why:
                t.state, t.why = "skipped", why

    def _scene_line(self, name: str) -> str:
        running = [t for t in self.tasks.values() if t.scene == name and t.state == "running"]
        parts = []
        for t in running:
            if not self._started(t):       # waiting for a worker (an old log's last line is not its progress)
                parts.append(f"{t.stage} queued")
                continue
            if t.stage == "train":
                p = train_progress(self.run_dir(name))
                if p is not None:
                    psnr = "" if p["psnr"] is None else f", PSNR {p['psnr']:.2f}"
                    eta = "" if not p["eta"] else f", ETA {p['eta']}"
                    parts.append(f"train step {p['step']}/{p['total']} ({p['pct']}%){psnr}{eta}")
                    continue
            parts.append(f"{t.stage} running")
        return f"  {name}: " + "; ".join(parts)

    def _overall_line(self, t0: float) -> str:
        states = [t.state for t in self.tasks.values()]
        n = len(states)
        finished = sum(s in ("done", "ok", "error", "failed", "skipped") for s in states)
        # submitted tasks that have begun, apart from those waiting for a worker or resources
        submitted = [t for t in self.tasks.values() if t.state == "running"]
        started = sum(self._started(t) for t in submitted)
        width = 20
        bar = "#" * int(round(width * finished / n)) if n else ""
        return (f"batch [{bar:<{width}}] {finished}/{n} tasks: {states.count('done')} complete before, "
                f"{states.count('ok')} done now, {states.count('error') + states.count('failed')} failed, "
                f"{states.count('skipped')} not run, {started} running, {len(submitted) - started} queued, "
                f"{states.count('todo')} waiting; {_fmt_time(time.time() - t0)} elapsed")

    def run(self) -> BatchResult:
        t0 = time.time()
        self.m.root.mkdir(parents=True, exist_ok=True)
        self.plan()
        self._mark_blocked()
        result = BatchResult(self.tasks)
        todo = sum(t.state == "todo" for t in self.tasks.values())
        self.say(f"batch {self.m.path}: {len(self.m.scenes)} scene(s), stages {', '.join(self.m.stages)}; "
                 f"{todo} of {len(self.tasks)} task(s) to run on {self.ex.describe()}; output in {self.m.root}")
        for t in self.tasks.values():
            if t.state == "failed":
                self.say(f"  {t.scene}: {t.stage} failed before on the same inputs (not repeated; "
                         f"--retry-failed runs it again): {t.why}")
        if todo:
            self.ex.capacity_check()
        last = time.monotonic()
        try:
            while True:
                self._submit_ready()
                if not any(t.state == "running" for t in self.tasks.values()):
                    break
                for key, res in self.ex.poll(timeout=0.5):
                    t = self.tasks[key]
                    t.result, t.ended = res, time.time()
                    result.ran.append(key)
                    took = _fmt_time(res.get("seconds", time.time() - (t.started or time.time())))
                    retried = f", attempt {res['attempt']}" if res.get("attempt", 1) > 1 else ""
                    if res.get("ok"):
                        t.state = "ok"
                        self.say(f"  {t.scene}: {t.stage} done in {took}{retried}")
                    else:
                        t.state, t.why = "error", res.get("error", "failed")
                        self.say(f"  {t.scene}: {t.stage} FAILED{retried}: {t.why}")
                if time.monotonic() - last >= self.interval:
                    last = time.monotonic()
                    for name in self.scenes:
                        if any(t.scene == name and t.state == "running" for t in self.tasks.values()):
                            self.say(self._scene_line(name))
                    self.say(self._overall_line(t0))
            self._submit_ready()          # marks what a failure left unrunnable
        except KeyboardInterrupt:
            # Ctrl-C / SIGTERM: stop the workers (a training saves a checkpoint on SIGTERM), write
            # the report of what is complete, and let the command line report the interruption
            self.say("batch: interrupted; stopping the running tasks (run the manifest again to go on)")
            self.ex.shutdown()
            write_report(self.m, None)
            raise
        finally:
            self.ex.shutdown()
        result.report = write_report(self.m, self.tasks)
        result.seconds = time.time() - t0
        self.say(self._overall_line(t0))
        return result


def run_batch(manifest: Manifest, executor, force: bool = False, retry_failed: bool = False,
              out: TextIO = None, interval: float = DEFAULT_INTERVAL) -> BatchResult:
    return Runner(manifest, executor, force, retry_failed, out, interval).run()
