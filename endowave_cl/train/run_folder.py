"""The run folder's safety rules, used by the Trainer.

* one writer at a time: ``RunLock`` (an flock on RUN/.lock holding the writer's pid; the kernel
  drops it when the process dies, so a stale lock is simply taken over);
* ``--restart`` moves the earlier run's files to RUN/previous_run/ (``retire_previous_run``) so
  checkpoint retention only ever sees the current run's checkpoints;
* retention (``prune_checkpoints``) never deletes the checkpoint just written nor a kept one (the
  best so far);
* a resume loads the newest checkpoint that reads back, setting unreadable newer ones aside as
  ``*.corrupt`` (``load_newest_good_checkpoint``);
* temporaries of killed writers are removed at start (``clean_stale_temporaries``);
* SIGINT / SIGTERM during training ask the loop to stop at the next step boundary (``StopFlag``),
  so the state saved on the way out is a consistent one.
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import json
import os
import re
import shutil
import signal
import threading
from pathlib import Path
from typing import Callable, Iterable, List, Optional

import numpy as np

from ..atomic import TEMP_RE, json_safe, stale_temporaries, write_bytes_atomic, write_json_atomic
from ..errors import EndowaveError
from ..checkpoint import checkpoint_path, checkpoints_by_step, load_newest_good_checkpoint, save_checkpoint
from ..gaussians import download
from .guard import DivergenceGuard

LOCK_NAME = ".lock"
PREVIOUS_RUN = "previous_run"
# what a run writes into its folder; --restart moves these to previous_run/
RUN_OUTPUTS = ("config.json", "train_log.json", "eval.json", "render", "train_curves.csv", "train_curves.png",
               "tensorboard")
RUN_OUTPUT_GLOBS = ("checkpoint_*.npz", "checkpoint_*.npz.corrupt", "model_t*.ply")
# temporaries of files only `train` writes in a run folder: under the lock they are stale whatever
# their pid (this also catches the pid-less names of earlier versions)
CHECKPOINT_FILE_RE = re.compile(r"^checkpoint_\d+\.npz(\.corrupt)?$")   # a model, readable or not
TRAIN_TEMP_RE = re.compile(r"^\.(checkpoint_\d+\.npz|config\.json|train_log\.json)\..*\.tmp$")


def _oserror(what: str, path, e: OSError) -> EndowaveError:
    return EndowaveError(f"{path}: cannot {what} ({e.strerror or e})")


def make_run_dir(run_dir) -> bool:
    """Create the run folder if needed, with one-line errors; True when it was created here."""
    run_dir = Path(run_dir)
    if run_dir.exists() and not run_dir.is_dir():
        raise EndowaveError(f"{run_dir}: exists and is not a folder (--out must be a run folder)")
    if run_dir.is_dir():
        if not os.access(run_dir, os.W_OK | os.X_OK):
            raise EndowaveError(f"{run_dir}: run folder is not writable")
        check_not_foreign(run_dir)
        return False
    for parent in run_dir.parents:
        if parent.exists():
            if not parent.is_dir():
                raise EndowaveError(f"{run_dir}: cannot create the run folder: {parent} is a file")
            break
    try:
        run_dir.mkdir(parents=True)
    except FileExistsError:
        return False
    except OSError as e:
        raise _oserror("create the run folder", run_dir, e) from None
    return True


def _is_ours(path: Path, keys) -> bool:
    """Whether path is a JSON object with all of keys (a file endowave-cl wrote)."""
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(d, dict) and all(k in d for k in keys)


def check_not_foreign(run_dir) -> None:
    """Refuse a folder whose config.json / train_log.json are not a run's (a user's own files that
    training would overwrite): an existing --out must be a run folder or hold neither file."""
    run_dir = Path(run_dir)
    for name, keys in (("config.json", ("scene", "iterations")), ("train_log.json", ("history",))):
        p = run_dir / name
        if p.exists() and not (p.is_file() and _is_ours(p, keys)):
            raise EndowaveError(f"{p}: this file is not an endowave-cl run's {name} and training would overwrite "
                                f"it; {run_dir} is not a run folder: use another --out")


class RunFolderBusy(EndowaveError):
    """Another process holds the run folder's lock: a state that passes, not bad input (batch does
    not record it as a data error that later runs refuse the scene for)."""


class RunLock:
    """Exclusive lock on a run folder for one training process.

    RUN/.lock is flock()ed for the lifetime of the lock and holds the owner's pid (for the error
    message).  The kernel releases an flock when its process dies, so a lock file left by a killed
    run does not block anyone.
    """

    def __init__(self, run_dir):
        self.path = Path(run_dir) / LOCK_NAME
        self.fd: Optional[int] = None

    def acquire(self) -> "RunLock":
        while True:
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError as e:
                raise _oserror("create the lock file", self.path, e) from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as e:
                os.close(fd)
                if e.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                    raise _oserror("lock the run folder", self.path, e) from None
                holder = self._holder()
                who = f"pid {holder}" if holder else "another process"
                raise RunFolderBusy(f"{self.path.parent}: run folder is in use by another endowave-cl train "
                                    f"({who}); wait for it to finish or use another --out") from None
            # the holder may have unlinked the file between our open and flock: lock the file that
            # is at the path now, or try again
            try:
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self.fd = fd
        return self

    def _holder(self) -> Optional[int]:
        try:
            text = self.path.read_text().strip()
            return int(text) if text else None
        except (OSError, ValueError):
            return None

    def release(self) -> None:
        if self.fd is None:
            return
        with contextlib.suppress(OSError):
            os.unlink(self.path)   # while still locked: nobody can be holding it
        os.close(self.fd)
        self.fd = None

    @property
    def held(self) -> bool:
        return self.fd is not None

    def __del__(self):
        self.release()


def clean_stale_temporaries(run_dir, log: Callable[[str], None] = print) -> List[Path]:
    """Remove temporaries left by killed writers: any pid-named one whose pid is gone, and (we hold
    the run lock, so no other trainer writes here) every temporary of the files only `train` writes."""
    run_dir = Path(run_dir)
    gone = set(stale_temporaries(run_dir)) | set(stale_temporaries(run_dir / "render"))
    for sub in (run_dir / "render" / "frames", run_dir / "render" / "depth"):
        gone |= set(stale_temporaries(sub))
    if run_dir.is_dir():
        gone |= {p for p in run_dir.iterdir() if TRAIN_TEMP_RE.match(p.name)
                 and not (TEMP_RE.match(p.name) and int(TEMP_RE.match(p.name).group("pid")) == os.getpid())}
    removed = []
    for p in sorted(gone):
        with contextlib.suppress(OSError):
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            else:
                p.unlink()
            removed.append(p)
    if removed:
        log(f"removed {len(removed)} temporary file(s) left by interrupted writers in {run_dir}")
    return removed


def prune_checkpoints(run_dir, keep: Iterable[Path], newest: int = 2) -> List[Path]:
    """Delete checkpoints except the ``newest`` highest steps and those in ``keep`` (the one just
    written and the best one).  Only the current run's checkpoints are in the folder (a restart
    retires the others), so step order is write order."""
    keep = {Path(p).resolve() for p in keep}
    cks = checkpoints_by_step(run_dir)
    keep |= {p.resolve() for p in cks[-newest:]} if newest > 0 else set()
    removed = []
    for p in cks:
        if p.resolve() not in keep:
            with contextlib.suppress(FileNotFoundError):
                p.unlink()
            removed.append(p)
    return removed


def retire_previous_run(run_dir, log: Callable[[str], None] = print) -> Optional[Path]:
    """Move an earlier run's outputs (checkpoints, config.json, logs, renders) to RUN/previous_run/,
    replacing an older previous_run/.  Nothing is deleted before the new folder is complete."""
    run_dir = Path(run_dir)
    items = [run_dir / n for n in RUN_OUTPUTS if (run_dir / n).exists()]
    for g in RUN_OUTPUT_GLOBS:
        items += sorted(run_dir.glob(g))
    if not items:
        return None
    final = run_dir / PREVIOUS_RUN
    if final.exists() and not any(CHECKPOINT_FILE_RE.match(p.name) for p in items):
        # a run that saved no model (killed before its first checkpoint) never replaces the
        # earlier one in previous_run/: only the files it wrote at its start go
        for p in items:
            if p.name in ("config.json", "train_log.json") and p.is_file():
                p.unlink()
        log(f"--restart: the interrupted run here saved no checkpoint; {final} is kept as it was")
        return final
    staging = run_dir / f".{PREVIOUS_RUN}.{os.getpid()}.new.tmp"
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir()
    # the newest model moves last: if we are killed half-way it is still in the run folder
    for p in items:
        os.replace(p, staging / p.name)
    old = None
    if final.exists():
        old = run_dir / f".{PREVIOUS_RUN}.{os.getpid()}.old.tmp"
        os.replace(final, old)
    os.replace(staging, final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    log(f"--restart: the earlier run's files are in {final}")
    return final


def scene_fingerprint(scene) -> dict:
    """What identifies the scene a run is trained on: frame count, size and a hash of the frames."""
    h = hashlib.sha1()
    for f in scene.frames:
        h.update(np.ascontiguousarray(f.image, np.float32).tobytes())
    return {"frames": len(scene.frames), "width": int(scene.width), "height": int(scene.height),
            "sha1": h.hexdigest()}


def check_same_scene(ck_extra: dict, scene, ckpt_path,
                     remedy: str = "use --restart to start over, or another --out") -> None:
    """Refuse to resume (or evaluate, render, export, view) a run on another scene, or the same
    folder regenerated, or at another size: the frames' fingerprint differs from the run's."""
    want = ck_extra.get("scene_fingerprint")
    if not isinstance(want, dict):
        return    # checkpoint from before fingerprints: nothing to compare
    have = scene_fingerprint(scene)
    if want == have:
        return
    was = ck_extra.get("scene", "another scene")
    if (want.get("width"), want.get("height")) != (have["width"], have["height"]):
        why = f"{want.get('width')}x{want.get('height')} frames there, {have['width']}x{have['height']} here"
    elif want.get("frames") != have["frames"]:
        why = f"{want.get('frames')} frames there, {have['frames']} here"
    else:
        why = "its frames differ"
    raise EndowaveError(f"{ckpt_path}: this run was trained on {was} and {scene.path} is not that scene "
                        f"({why}); {remedy}")


def _has_history(log_file: Path) -> bool:
    try:
        d = json.loads(log_file.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(d, dict) and bool(d.get("history"))


class StopRequested(KeyboardInterrupt):
    """SIGINT or SIGTERM asked training to stop; the state at the step boundary was saved."""


class StopFlag:
    """Set by the SIGINT / SIGTERM handler that RunSession installs while training: the loop stops
    at the next step boundary, so the state saved on the way out is a consistent one."""

    def __init__(self):
        self.requested: Optional[str] = None

    def request(self, why: str) -> None:
        self.requested = why


class RunSession:
    """One training process's hold on its run folder; the Trainer calls it at a few points:

    ``RunSession(run_dir, log, resume)``   create the folder, take the lock, remove stale temporaries
    ``resume_point(scene)``                the newest readable checkpoint (same scene) or (None, None)
    ``start(trainer, ck)``                 after the model is ready: retire an earlier run
                                           (--restart), restore the sampling state, write config.json
    ``poll(trainer)``                      top of each step: a SIGINT / SIGTERM saves and stops
    ``after_step(trainer, step, ema)``     the divergence guard
    ``save(trainer)``                      guarded checkpoint + retention + train_log.json
    ``finish(trainer, metrics)``           final train_log.json, release the lock
    ``fail(exc)``                          record why the run stopped, release the lock
    ``abort()``                            a start that failed: release, remove a folder made for it
    """

    def __init__(self, run_dir, log: Callable[[str], None] = print, resume: bool = True):
        self.run_dir = Path(run_dir)
        self.log = log
        self.resume = resume
        self.created = make_run_dir(self.run_dir)
        self.lock = RunLock(self.run_dir)
        try:
            self.lock.acquire()
        except BaseException:
            self._remove_if_created()
            raise
        clean_stale_temporaries(self.run_dir, log)
        self.stop = StopFlag()
        self._old_handlers = None
        self.guard = None
        self.ema: Optional[dict] = None
        self.best = None                  # (training PSNR, path) of the best checkpoint so far
        self.last_saved: Optional[Path] = None
        self.fingerprint = None

    # -------------------------------------------------------------- start
    def resume_point(self, scene):
        if not self.resume:
            return None, None
        path, ck = load_newest_good_checkpoint(self.run_dir, self.log, set_aside=True)
        if ck is not None:
            check_same_scene(ck["extra"], scene, path)
            self.last_saved = path
            return path, ck
        # nothing to resume from: starting at step 0 would overwrite the log of a run whose
        # checkpoints were all set aside as unreadable (or removed); say so instead
        corrupt = sorted(self.run_dir.glob("checkpoint_*.npz.corrupt"))
        log_file = self.run_dir / "train_log.json"
        if corrupt:
            raise EndowaveError(f"{self.run_dir}: no readable checkpoint to resume from ({len(corrupt)} set aside as "
                                f"unreadable, e.g. {corrupt[-1].name}); use --restart to start over (the earlier "
                                f"files move to previous_run/)")
        if log_file.is_file() and _has_history(log_file):
            raise EndowaveError(f"{log_file}: this run logged training steps but has no checkpoint to resume from; "
                                f"use --restart to start over (the earlier files move to previous_run/)")
        return None, None

    def start(self, trainer, ck) -> None:
        if not self.resume:
            retire_previous_run(self.run_dir, self.log)
        self.fingerprint = scene_fingerprint(trainer.scene)
        extra = ck["extra"] if ck is not None else {}
        center = extra.get("center")
        if center is None or np.size(center) != 3:
            g_means = trainer.params["means"].get()
            center = g_means[:, :3].mean(0) if len(g_means) else np.zeros(3)
        self.center = np.asarray(center, np.float64).reshape(3)
        self.guard = DivergenceGuard(trainer.extent, self.center)
        if ck is not None:
            # the state an uninterrupted run would have at this step: frame sampling, the loss EMA,
            # the densification statistics, the log so far
            if isinstance(extra.get("rng_state"), dict):
                trainer.rng.bit_generator.state = extra["rng_state"]
            self.ema = extra.get("ema")
            trainer.history = [h for h in extra.get("history", []) if h.get("step", 0) <= trainer.step]
            for name, arr in trainer.stats.items():
                saved = extra.get(f"stats_{name}")
                if isinstance(saved, np.ndarray) and saved.shape == arr.shape and saved.dtype == arr.dtype:
                    arr.set(saved)
            psnr = extra.get("train_psnr")
            if isinstance(psnr, (int, float)):
                self.best = (float(psnr), self.last_saved)
        # the run folder describes itself (render / eval / export read this); written only now
        # that the checkpoint loaded or the model initialised
        write_bytes_atomic(self.run_dir / "config.json", json.dumps(json_safe(
            {"scene": str(Path(trainer.scene.path).resolve()), **trainer.cfg.to_dict()}),
            indent=1, allow_nan=False).encode())

    def _remove_if_created(self) -> None:
        if self.created:
            with contextlib.suppress(OSError):
                self.run_dir.rmdir()      # only when empty: never removes anything written

    def abort(self) -> None:
        self.lock.release()
        self._remove_if_created()

    # -------------------------------------------------------------- the loop
    def _install_handlers(self) -> None:
        if self._old_handlers is not None or threading.current_thread() is not threading.main_thread():
            return
        names = {signal.SIGINT: "SIGINT", signal.SIGTERM: "SIGTERM"}

        def handler(signum, frame):
            if self.stop.requested is not None:   # a second signal: stop at once
                raise KeyboardInterrupt
            self.stop.request(names.get(signum, str(signum)))
        self._old_handlers = {s: signal.signal(s, handler) for s in names}

    def _restore_handlers(self) -> None:
        if self._old_handlers is not None:
            for s, h in self._old_handlers.items():
                signal.signal(s, h)
            self._old_handlers = None

    def poll(self, trainer) -> None:
        """At a step boundary: install the signal handlers (first call); after a SIGINT / SIGTERM
        save the state and raise StopRequested."""
        self._install_handlers()
        why = self.stop.requested
        if why is None:
            return
        self._restore_handlers()
        try:
            path = self.save(trainer)
        except BaseException:
            self.lock.release()
            raise
        self.lock.release()
        raise StopRequested(f"stopped by {why} at step {trainer.step}; saved {path}; "
                            f"run the same train command to resume")

    def after_step(self, trainer, step: int, ema: Optional[dict]) -> None:
        self.ema = None if ema is None else {k: float(v) for k, v in ema.items()}
        try:
            self.guard.observe(step, None if not ema else ema.get("psnr"))
            if step % trainer.cfg.log_every == 0:
                self.guard.check(step, trainer.params, trainer.rt)
        except EndowaveError as e:
            raise self.fail(trainer, e) from None

    def check_parameters(self, trainer) -> None:
        """The guard's parameter test now (before density control reads the parameters)."""
        try:
            self.guard.check(trainer.step, trainer.params, trainer.rt)
        except EndowaveError as e:
            raise self.fail(trainer, e) from None

    def fail(self, trainer, exc: EndowaveError) -> EndowaveError:
        """Record why the run stopped in train_log.json, release the lock; returns the exception
        to raise, its message naming the checkpoint to continue from."""
        self._restore_handlers()
        good = f"the last good checkpoint is {self.last_saved}" if self.last_saved else "no checkpoint was saved"
        exc = type(exc)(f"{exc}; stopped, {good}")
        with contextlib.suppress(Exception):
            self.write_log(trainer, None, stopped=str(exc))
        self.lock.release()
        return exc

    # -------------------------------------------------------------- saving
    def write_log(self, trainer, final, stopped: Optional[str] = None) -> None:
        log = {"final": final, "history": trainer.history}
        if stopped:
            log["stopped"] = stopped
        write_json_atomic(self.run_dir / "train_log.json", log)

    def save(self, trainer) -> Path:
        try:
            self.guard.check(trainer.step, trainer.params, trainer.rt)
        except EndowaveError as e:
            raise self.fail(trainer, e) from None
        if not self.lock.held:
            raise EndowaveError(f"{self.run_dir}: the run folder lock was released; not saving")
        path = checkpoint_path(self.run_dir, trainer.step)
        psnr = None if not self.ema else self.ema.get("psnr")
        extra = {"extent": trainer.extent, "scene": str(trainer.scene.path), "world_scale": trainer.scene.world_scale,
                 "scene_fingerprint": self.fingerprint, "center": self.center,
                 "rng_state": trainer.rng.bit_generator.state, "ema": self.ema,
                 "history": trainer.history, "train_psnr": psnr}
        for name, arr in trainer.stats.items():
            extra[f"stats_{name}"] = arr.get()
        save_checkpoint(path, download(trainer.params), trainer.adam.state_dict(), trainer.step,
                        trainer.cfg.to_dict(), extra)
        self.last_saved = path
        if psnr is not None and np.isfinite(psnr) and (self.best is None or psnr >= self.best[0]
                                                       or self.best[1] is None or not self.best[1].exists()):
            self.best = (float(psnr), path)
        keep = [path] + ([self.best[1]] if self.best and self.best[1] is not None else [])
        prune_checkpoints(self.run_dir, keep, newest=2)
        self.write_log(trainer, None)
        return path

    def finish(self, trainer, metrics) -> None:
        self.write_log(trainer, metrics)
        self._restore_handlers()
        self.lock.release()
