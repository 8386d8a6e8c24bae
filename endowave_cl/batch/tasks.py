"""One batch task: a scene through one stage, by the stage's own command (``endowave_cl.commands``).

A task writes only inside its run folder ROOT/<scene>: the command's own outputs (atomic, as the
commands write them) and, in RUN/batch/:

  <stage>.log           the command's output, appended, one header line per attempt
  <stage>.attempt.json  the current attempt (batch id, attempt number, pid, host)
  <stage>.json          written last, when the stage succeeded: what it ran on (the model's token,
                        the settings and options) -- the completion record a re-run reads
  <stage>.failed.json   a failure: the one-line error, its kind and the signature of the inputs

The flow stage also fills the flow cache (outside the run folder; $ENDOWAVE_CL_CACHE/flow), which
is keyed by the frames and written atomically, so concurrent or repeated writers are harmless.

``run_task`` runs in a worker: in-process in a Ray worker, or as ``python -m
endowave_cl.batch.tasks`` (spec on stdin, result as the last stdout line) in the process pool.
"""
from __future__ import annotations

import contextlib
import gc
import hashlib
import json
import os
import signal
import socket
import sys
import threading
import time
import traceback
import uuid
import warnings
from pathlib import Path
from typing import Any, Dict, List, Optional

from .. import cli
from ..atomic import stale_temporaries, write_json_atomic
from ..errors import EndowaveError
from ..runtime import KernelBuildError, OpenCLUnavailable
from ..train.run_folder import RunFolderBusy, RunLock, make_run_dir, retire_previous_run
from .manifest import MAX_TASK_CPUS, setting

BATCH_DIR = "batch"
RESULT_PREFIX = "ENDOWAVE_BATCH_RESULT "
PROGRESS_INTERVAL = 2.0           # seconds between the plain progress lines a task's log gets
BUSY_KIND = "busy"               # the run folder was locked by another process (an orphaned worker): not sticky
STICKY_KINDS = ("data",)          # failures a re-run does not repeat while the inputs are unchanged


# ---------------------------------------------------------------------------- run folder records
def batch_dir(run_dir) -> Path:
    return Path(run_dir) / BATCH_DIR


def read_json(path) -> Optional[Any]:
    """The JSON in ``path``, or None when it is missing or unreadable (a record that cannot be read
    counts as absent: the stage runs again)."""
    try:
        with open(path, "rb") as f:
            return json.loads(f.read())
    except (OSError, ValueError):
        return None


def record(run_dir, stage: str, kind: str = "") -> Path:
    """RUN/batch/<stage><kind>.json (kind: "", ".attempt", ".failed")."""
    return batch_dir(run_dir) / f"{stage}{kind}.json"


def train_final(run_dir) -> Optional[dict]:
    """train_log.json's "final" (the metrics of a finished training), or None."""
    log = read_json(Path(run_dir) / "train_log.json")
    final = log.get("final") if isinstance(log, dict) else None
    return final if isinstance(final, dict) else None


def model_token(run_dir) -> Optional[str]:
    """What identifies the trained model the later stages ran on: the batch train record's token,
    else (a run trained outside batch) its final step; None when training has not finished."""
    final = train_final(run_dir)
    if final is None:
        return None
    rec = read_json(record(run_dir, "train"))
    if isinstance(rec, dict) and rec.get("token"):
        return str(rec["token"])
    return f"step {final.get('step')}"


def scene_signature(scene_path, options: dict) -> str:
    """A hash of the scene folder's files (names, sizes, modification times, two levels deep) and
    the task's options: a data failure is repeated from its record while this is unchanged."""
    h = hashlib.sha1(json.dumps(options, sort_keys=True, default=str).encode())
    root = Path(scene_path)
    if not root.is_dir():
        h.update(b"missing")
        return h.hexdigest()

    def walk(d: Path, depth: int):
        try:
            entries = sorted(os.scandir(d), key=lambda e: e.name)
        except OSError:
            h.update(f"unreadable {d}".encode())
            return
        for e in entries:
            try:
                st = e.stat()
            except OSError:
                continue
            h.update(f"{os.path.relpath(e.path, root)}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
            if depth > 0 and e.is_dir():
                walk(Path(e.path), depth - 1)
    walk(root, 1)
    return h.hexdigest()


# ---------------------------------------------------------------------------- the task description
def _value_text(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    return repr(v) if isinstance(v, float) else str(v)


def stage_options(manifest, scene, stage: str) -> dict:
    """What a stage's result depends on besides the scene's frames: its completion record stores
    this, and a re-run with other options does the stage again."""
    if stage == "flow":
        return {"method": setting(scene, "flow_method"), "downscale": setting(scene, "downscale"),
                "max_pixels": setting(scene, "flow_max_pixels")}
    if stage == "train":
        return {"settings": dict(scene.settings)}
    if stage == "eval":
        return {"baselines": manifest.eval["baselines"]}
    if stage == "render":
        return {"all": manifest.render["all"], "video": manifest.render["video"], "fps": manifest.render["fps"]}
    if stage == "export":
        return {"time": manifest.export["time"]}
    raise ValueError(stage)


def export_path(run_dir, t: float) -> Path:
    return Path(run_dir) / f"model_t{t:.3f}.ply"    # the export command's default name


def command_argv(manifest, scene, stage: str, run_dir) -> List[str]:
    """The endowave-cl command line of a stage (without --restart, which the worker adds)."""
    run, src = str(run_dir), str(scene.path)
    dev = manifest.resources.get("device")
    device = ["--device", dev] if dev else []
    if stage == "flow":
        return ["flow", src, "--method", setting(scene, "flow_method"),
                "--downscale", _value_text(float(setting(scene, "downscale"))),
                "--max-pixels", str(int(setting(scene, "flow_max_pixels"))), "--no-progress"]
    if stage == "train":
        sets = [a for k, v in scene.settings.items() for a in ("--set", f"{k}={_value_text(v)}")]
        return ["train", src, "--out", run, *sets, *device]
    if stage == "eval":
        return ["eval", run, "--scene", src, "--fps-runs", str(manifest.eval["fps_runs"]),
                *([] if manifest.eval["baselines"] else ["--no-baselines"]), *device]
    if stage == "render":
        r = manifest.render
        return ["render", run, "--scene", src, "--fps", _value_text(float(r["fps"])),
                *(["--all"] if r["all"] else []), *([] if r["video"] else ["--no-video"]), *device]
    if stage == "export":
        t = float(manifest.export["time"])
        return ["export", run, "--time", _value_text(t), "--out", str(export_path(run_dir, t))]
    raise ValueError(stage)


def task_env(manifest) -> Dict[str, str]:
    """Environment of a task's process: plain progress lines (the driver reads them from the log)
    and, for PoCL and torch, as many threads as the task has CPU cores (two tasks on a 2-core
    machine would otherwise each start 2 threads per kernel and contend)."""
    cores = str(min(MAX_TASK_CPUS, max(1, int(manifest.resources["cpus"]))))
    env = {"ENDOWAVE_PROGRESS": "plain", "ENDOWAVE_PROGRESS_INTERVAL": str(PROGRESS_INTERVAL)}
    # PoCL's CPU thread count: POCL_MAX_PTHREAD_COUNT up to PoCL 4 (the pyopencl wheels' PoCL),
    # POCL_CPU_MAX_CU_NUM from PoCL 5; a value the user set wins
    for var in ("POCL_MAX_PTHREAD_COUNT", "POCL_CPU_MAX_CU_NUM", "OMP_NUM_THREADS"):
        env[var] = os.environ.get(var, cores)
    return env


def make_spec(manifest, scene, stage: str, run_dir, batch_id: str, restart: bool, signature: str) -> dict:
    """Everything a worker needs, as plain JSON-able data (it travels to Ray or a child process)."""
    return {"scene": scene.name, "scene_path": str(scene.path), "stage": stage, "run_dir": str(run_dir),
            "argv": command_argv(manifest, scene, stage, run_dir), "options": stage_options(manifest, scene, stage),
            "env": task_env(manifest), "batch_id": batch_id, "restart": bool(restart), "signature": signature}


# ---------------------------------------------------------------------------- completion (driver)
def _train_state(manifest, scene, run_dir) -> tuple:
    """("done" | "todo", why, restart) of the train stage, from the run folder's files."""
    final = train_final(run_dir)
    rec = read_json(record(run_dir, "train"))
    opts = stage_options(manifest, scene, "train")
    if isinstance(rec, dict) and isinstance(rec.get("options"), dict) and rec["options"] != opts:
        old = dict(rec["options"].get("settings") or {})
        new = dict(opts["settings"])
        old.pop("iterations", None), new.pop("iterations", None)
        if old != new or setting(scene, "minutes") > 0:
            return "todo", "settings changed: training starts over (earlier run kept in previous_run/)", True
        # only the step count changed: training continues from the finished run's last checkpoint
        return "todo", "iterations changed: training continues", False
    if final is None:
        return "todo", ("resuming an unfinished run" if (Path(run_dir) / "train_log.json").exists() else ""), False
    if rec is None and setting(scene, "minutes") <= 0 and int(final.get("step", 0)) < setting(scene, "iterations"):
        return "todo", "training continues to the manifest's iterations", False
    return "done", f"trained, {final.get('step')} steps", False


def stage_status(manifest, scene, stage: str, run_dir, force: bool = False, retry_failed: bool = False,
                 signature: Optional[str] = None) -> tuple:
    """(state, why, restart) of a stage of a scene, decided from the run folder's files:
    "done" (complete for the manifest's current settings and the current model), "failed" (a data
    error recorded for these same inputs: a re-run does not repeat it) or "todo".  ``restart``:
    training must start over (--force, or settings other than iterations changed)."""
    failed = read_json(record(run_dir, stage, ".failed"))
    if (not force and not retry_failed and isinstance(failed, dict) and failed.get("kind") in STICKY_KINDS
            and signature is not None and failed.get("signature") == signature):
        return "failed", str(failed.get("error")), False
    if force:
        return "todo", "--force", stage == "train"
    if stage == "train":
        return _train_state(manifest, scene, run_dir)
    rec = read_json(record(run_dir, stage))
    if not isinstance(rec, dict) or rec.get("options") != stage_options(manifest, scene, stage):
        return "todo", "", False
    if stage != "flow" and rec.get("model") != model_token(run_dir):
        return "todo", "the model changed", False
    if stage == "eval" and not (Path(run_dir) / "eval.json").is_file():
        return "todo", "eval.json is missing", False
    if stage == "export" and not export_path(run_dir, float(manifest.export["time"])).is_file():
        return "todo", "the PLY is missing", False
    return "done", "", False


# ---------------------------------------------------------------------------- in the worker
def _clear_caches() -> None:
    """Per-scene caches of evaluation (flow references, baseline scores) would otherwise grow in a
    long-lived Ray worker with every scene it evaluates."""
    for mod, name in (("endowave_cl.evaluation", "_FLOW_CACHE"), ("endowave_cl.baselines", "_CACHE")):
        cache = getattr(sys.modules.get(mod), name, None)
        if isinstance(cache, dict):
            cache.clear()
    gc.collect()


def _run_command(argv: List[str]) -> Dict[str, Any]:
    """The command, in this process: {"ok"} or {"ok": False, "kind", "error"} with the one-line
    message the CLI would print.  kind "data": bad input the user fixes (EndowaveError: a scene, a
    setting, a run folder); others: "device", "io", "interrupted", "unexpected"."""
    warnings.filterwarnings("ignore", message="Non-empty compiler output")   # as cli.main does
    name = f"endowave-cl {argv[0]}"
    try:
        args = cli.build_parser(argv).parse_args(argv)
    except SystemExit:
        return {"ok": False, "kind": "unexpected", "error": f"{name}: error: bad arguments {argv[1:]}"}
    except ImportError as e:        # a dependency of the command is missing: a broken install
        return {"ok": False, "kind": "unexpected", "error": f"{name}: error: {e}"}
    try:
        rc = int(args._module.run(args) or 0)
        if rc != 0:
            return {"ok": False, "kind": "unexpected", "error": f"{name}: exit status {rc}"}
        return {"ok": True}
    except EndowaveError as e:
        kind = BUSY_KIND if isinstance(e, RunFolderBusy) else "data"
        return {"ok": False, "kind": kind, "error": f"{name}: error: {e}"}
    except (OpenCLUnavailable, KernelBuildError) as e:
        return {"ok": False, "kind": "device", "error": f"{name}: error: {e}"}
    except OSError as e:
        return {"ok": False, "kind": "io", "error": f"{name}: error: {cli._oserror_text(e)}"}
    except KeyboardInterrupt as e:
        return {"ok": False, "kind": "interrupted", "error": f"{name}: {e or 'interrupted'}"}
    except MemoryError:
        return {"ok": False, "kind": "unexpected", "error": f"{name}: error: out of memory"}
    except Exception as e:  # noqa: BLE001  a bug: one line in the report, the traceback in the log
        traceback.print_exc()
        first = str(e).splitlines()[0] if str(e) else ""
        return {"ok": False, "kind": "unexpected", "error": f"{name}: error: unexpected {type(e).__name__}: {first}"}


def _retire(run_dir: Path) -> Dict[str, Any]:
    """--force or changed settings: move the earlier run's files to RUN/previous_run/ (what
    ``train --restart`` does), here under the run folder lock and once per batch invocation, so
    that a retried attempt resumes the new run instead of restarting it again."""
    try:
        make_run_dir(run_dir)
        lock = RunLock(run_dir).acquire()
        try:
            retire_previous_run(run_dir)
        finally:
            lock.release()
    except EndowaveError as e:
        kind = BUSY_KIND if isinstance(e, RunFolderBusy) else "data"
        return {"ok": False, "kind": kind, "error": f"endowave-cl train: error: {e}"}
    return {"ok": True}


def run_task(spec: dict) -> dict:
    """Run one (scene, stage) task here and record the outcome in RUN/batch/.  Returns the result
    {"ok", "kind", "error", "seconds", "attempt", "pid", "host"}.  A process killed in here leaves
    at most a stale temporary (removed by the next attempt) and its last atomic checkpoint."""
    t0 = time.time()
    run_dir, stage = Path(spec["run_dir"]), spec["stage"]
    bdir = batch_dir(run_dir)
    try:
        bdir.mkdir(parents=True, exist_ok=True)
    except OSError as e:            # e.g. the root not writable on this node: fails alone, one line
        return {"ok": False, "kind": "io", "error": f"{bdir}: cannot create the folder ({e.strerror or e})",
                "seconds": time.time() - t0, "started": t0, "attempt": 1, "pid": os.getpid(),
                "host": socket.gethostname(), "scene": spec["scene"], "stage": stage}
    for p in stale_temporaries(bdir):              # records half-written by a killed attempt
        with contextlib.suppress(OSError):
            p.unlink()
    os.environ.update(spec.get("env", {}))
    # attempt number: an attempt record of the same batch invocation means this is a retry after
    # the worker died (Ray or the pool re-ran us); a retry resumes training instead of restarting
    prev = read_json(record(run_dir, stage, ".attempt"))
    retry = isinstance(prev, dict) and prev.get("batch_id") == spec["batch_id"]
    attempt = int(prev.get("attempt", 1)) + 1 if retry else 1
    host, pid = socket.gethostname(), os.getpid()
    argv = list(spec["argv"])
    with open(bdir / f"{stage}.log", "a", buffering=1) as log:
        log.write(f"== batch {spec['batch_id']}: attempt {attempt}, pid {pid} on {host}, "
                  f"{time.strftime('%Y-%m-%d %H:%M:%S')}: endowave-cl {' '.join(argv)}\n")
        with contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
            try:
                res = {"ok": True}
                if stage == "train" and spec.get("restart") and not retry:
                    res = _retire(run_dir)
                # written after the retirement: a retry never retires the run its first attempt began
                write_json_atomic(record(run_dir, stage, ".attempt"), {
                    "batch_id": spec["batch_id"], "attempt": attempt, "pid": pid, "host": host, "started": t0})
                if res["ok"]:
                    res = _run_command(argv)
            finally:
                _clear_caches()
        if not res["ok"]:
            log.write(res["error"] + "\n")
    res.update({"seconds": time.time() - t0, "started": t0, "attempt": attempt, "pid": pid, "host": host,
                "scene": spec["scene"], "stage": stage})
    if res["ok"]:
        done = {"stage": stage, "options": spec["options"], "seconds": res["seconds"], "attempt": attempt,
                "host": host, "finished": time.time()}
        if stage == "train":
            done["token"] = uuid.uuid4().hex        # a new model: later stages must run on it
        elif stage != "flow":
            done["model"] = model_token(run_dir)
        write_json_atomic(record(run_dir, stage), done)
        with contextlib.suppress(FileNotFoundError):
            os.unlink(record(run_dir, stage, ".failed"))
    else:
        write_json_atomic(record(run_dir, stage, ".failed"),
                          {"stage": stage, "error": res["error"], "kind": res["kind"],
                           "signature": spec["signature"], "attempt": attempt})
    return res


PARENT_POLL = 1.0        # seconds between the pool worker's checks that its driver is alive
PARENT_GRACE = 60.0      # seconds a worker has to save and stop after its driver died, then it exits


def _die_with_parent(ppid: int) -> None:
    """A watchdog thread: when the driver that started this worker is gone (SIGKILL, a crash: the
    worker is re-parented), SIGTERM ourselves (train saves a checkpoint and stops, as on a
    Ctrl-C of the driver), and exit outright if that has not ended us within PARENT_GRACE."""
    def watch():
        while os.getppid() == ppid and ppid != 1:
            time.sleep(PARENT_POLL)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(PARENT_GRACE)
        os._exit(143)
    threading.Thread(target=watch, name="die-with-parent", daemon=True).start()


def main() -> int:
    """The process pool's worker: a spec as JSON on stdin, the result as the last stdout line.
    It dies with its driver (_die_with_parent)."""
    _die_with_parent(os.getppid())
    spec = json.loads(sys.stdin.read())
    res = run_task(spec)
    sys.stdout.write(RESULT_PREFIX + json.dumps(res) + "\n")
    sys.stdout.flush()
    return 0


if __name__ == "__main__":
    main()
    # everything is written (atomically) and closed: skip the interpreter's teardown of torch and
    # OpenCL, which took 1-2 s per task of the pool on a busy 2-core machine
    os._exit(0)
