"""Run folders that cannot lose a model (issue #14): lock, --restart, retention, resume state,
corrupt-checkpoint fallback, stale temporaries, SIGTERM, config.json only on a real start."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from conftest import make_tiny_scene, tiny_config


@pytest.fixture(scope="module")
def other_scene(tmp_path_factory):
    return make_tiny_scene(tmp_path_factory, "other", seed=4)


def _cfg(**kw):
    return tiny_config(**{**dict(iterations=20, init_points=500, densify_from=10, densify_every=10,
                                 densify_until=30, log_every=5, use_flow=False), **kw})


def _trainer(scene_path, run, rt, resume=True, msgs=None, **kw):
    from endowave_cl.data.scene import load_scene
    from endowave_cl.train.trainer import Trainer
    return Trainer(load_scene(scene_path), _cfg(**kw), run, rt,
                   log=(msgs.append if msgs is not None else (lambda s: None)), resume=resume)


def _steps(run):
    from endowave_cl.checkpoint import checkpoints_by_step
    return [int(p.name[11:18]) for p in checkpoints_by_step(run)]


def _cli(*args, **kw):
    return subprocess.run([sys.executable, "-m", "endowave_cl", *args], capture_output=True, text=True,
                          timeout=600, **kw)


def _one_line_error(r, *words):
    """exit 1, one line on stderr naming each of ``words``, no traceback."""
    err = r.stderr.strip()
    assert r.returncode == 1, (r.returncode, r.stderr)
    assert "Traceback" not in r.stderr and len(err.splitlines()) == 1, r.stderr
    for w in words:
        assert w in err, (w, err)
    return err


# ------------------------------------------------------------------ restart and retention
def test_restart_keeps_the_new_checkpoint_and_retires_the_old_run(rt, tiny_scene, tmp_path):
    run = tmp_path / "run"
    _trainer(tiny_scene, run, rt, iterations=40, checkpoint_every=20).train(progress=False)
    assert _steps(run) == [20, 40]
    tr = _trainer(tiny_scene, run, rt, resume=False, iterations=10)
    tr.train(progress=False)
    # before the fix, keep-the-two-newest by step deleted the new checkpoint_0000010 and kept 20, 40
    assert _steps(run) == [10]
    assert sorted(p.name for p in (run / "previous_run").iterdir()) == [
        "checkpoint_0000020.npz", "checkpoint_0000040.npz", "config.json", "train_curves.csv", "train_curves.png",
        "train_log.json"]
    assert json.loads((run / "train_log.json").read_text())["final"]["step"] == 10


def test_retention_keeps_the_just_written_and_the_best(tmp_path):
    from endowave_cl.train.run_folder import prune_checkpoints
    for s in (10, 20, 30, 40):
        (tmp_path / f"checkpoint_{s:07d}.npz").write_bytes(b"x")
    prune_checkpoints(tmp_path, keep=[tmp_path / "checkpoint_0000010.npz"], newest=2)
    assert _steps(tmp_path) == [10, 30, 40]


# ------------------------------------------------------------------ lock
def test_lock_refuses_a_second_writer_naming_its_pid_and_takes_over_a_stale_one(tmp_path):
    from endowave_cl.errors import EndowaveError
    from endowave_cl.train.run_folder import LOCK_NAME, RunLock
    a = RunLock(tmp_path).acquire()
    with pytest.raises(EndowaveError, match=f"in use by another endowave-cl train \\(pid {os.getpid()}\\)"):
        RunLock(tmp_path).acquire()
    a.release()
    assert not (tmp_path / LOCK_NAME).exists()
    (tmp_path / LOCK_NAME).write_text("999999999\n")      # left by a killed run: no flock held
    b = RunLock(tmp_path).acquire()
    assert (tmp_path / LOCK_NAME).read_text().strip() == str(os.getpid())
    b.release()


def test_second_train_on_a_locked_folder_fails_and_changes_nothing(rt, tiny_scene, tmp_path):
    from endowave_cl.errors import EndowaveError
    run = tmp_path / "run"
    _trainer(tiny_scene, run, rt, iterations=10).train(progress=False)
    first = _trainer(tiny_scene, run, rt, iterations=20)       # holds the lock until it trains
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file() and p.name != ".lock"}
    with pytest.raises(EndowaveError, match="in use"):
        _trainer(tiny_scene, run, rt, resume=False, iterations=5)
    after = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file() and p.name != ".lock"}
    assert after == before
    first.train(progress=False)
    assert _steps(run)[-1] == 20


# ------------------------------------------------------------------ config.json, scene check, fallback
def test_failed_start_leaves_no_config_json_and_no_folder(rt, tiny_scene, tmp_path, monkeypatch):
    from endowave_cl.errors import EndowaveError
    from endowave_cl.train.trainer import Trainer

    def boom(self):
        raise EndowaveError("flow failed")
    monkeypatch.setattr(Trainer, "_prepare_targets", boom)
    with pytest.raises(EndowaveError, match="flow failed"):
        _trainer(tiny_scene, tmp_path / "new", rt)
    assert not (tmp_path / "new").exists()


def test_corrupt_newest_checkpoint_falls_back_and_config_is_untouched_when_all_are_bad(rt, tiny_scene, tmp_path):
    from endowave_cl.errors import EndowaveError
    run = tmp_path / "run"
    _trainer(tiny_scene, run, rt, iterations=20, checkpoint_every=10).train(progress=False)
    newest = run / "checkpoint_0000020.npz"
    newest.write_bytes(newest.read_bytes()[:1000])
    msgs = []
    tr = _trainer(tiny_scene, run, rt, msgs=msgs, iterations=30)
    assert tr.step == 10 and any("checkpoint_0000020.npz" in m and "older" in m for m in msgs)
    assert (run / "checkpoint_0000020.npz.corrupt").exists()
    tr.train(progress=False)
    assert _steps(run) == [10, 30]           # the set-aside file no longer outranks the new ones
    # every checkpoint corrupt: the error names the newest, config.json stays as it was
    for p in run.glob("checkpoint_*.npz"):
        p.write_bytes(b"junk")
    cfg_before = (run / "config.json").read_bytes()
    with pytest.raises(EndowaveError, match="checkpoint_0000030.npz: not a readable checkpoint"):
        _trainer(tiny_scene, run, rt, iterations=99)
    assert (run / "config.json").read_bytes() == cfg_before


def test_resume_on_another_scene_is_refused(rt, tiny_scene, other_scene, tmp_path):
    from endowave_cl.errors import EndowaveError
    run = tmp_path / "run"
    _trainer(tiny_scene, run, rt, iterations=5).train(progress=False)
    with pytest.raises(EndowaveError, match="is not that scene"):
        _trainer(other_scene, run, rt, iterations=10)
    _trainer(other_scene, run, rt, resume=False, iterations=5).train(progress=False)   # --restart works


# ------------------------------------------------------------------ resume = uninterrupted
def test_interrupted_and_resumed_equals_uninterrupted(rt, tiny_scene, tmp_path):
    from endowave_cl.gaussians import download
    from endowave_cl.train.run_folder import StopRequested
    kw = dict(iterations=36, checkpoint_every=0, densify_from=10, densify_every=10, densify_until=30)
    full = _trainer(tiny_scene, tmp_path / "full", rt, **kw)
    full.train(progress=False)

    part = _trainer(tiny_scene, tmp_path / "part", rt, **kw)
    orig = part.schedule_step

    def step_then_signal(order):    # a SIGINT arriving during step 17 (mid-way between densifications),
        out = orig(order)           # whichever kind of step the schedule draws there
        if part.step == 17:
            part._run.stop.request("SIGINT")
        return out
    part.schedule_step = step_then_signal
    with pytest.raises(StopRequested, match="step 17"):
        part.train(progress=False)
    resumed = _trainer(tiny_scene, tmp_path / "part", rt, **kw)
    assert resumed.step == 17
    resumed.train(progress=False)

    a, b = download(full.params), download(resumed.params)
    for name in ("means", "scales", "opacity", "sh"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    # the same history but the wall time of the steps (step_ms)
    la, lb = ([{k: v for k, v in h.items() if k != "step_ms"} for h in json.loads(
        (tmp_path / d / "train_log.json").read_text())["history"]] for d in ("full", "part"))
    assert la == lb and [h["step"] for h in lb] == [5, 10, 15, 20, 25, 30, 35, 36]


# ------------------------------------------------------------------ temporaries, permissions
def test_stale_temporaries_are_removed_at_start(rt, tiny_scene, tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    dead = run / ".checkpoint_0000010.npz.999999999.abcd.tmp"      # pid 999999999 does not run
    legacy = run / ".train_log.json.k2j3h4.tmp"                     # pid-less name of older versions
    alive = run / f".eval.json.{os.getppid()}.abcd.tmp"             # a live writer: kept
    for p in (dead, legacy, alive):
        p.write_bytes(b"x" * 10)
    _trainer(tiny_scene, run, rt, iterations=5).train(progress=False)
    assert not dead.exists() and not legacy.exists() and alive.exists()


def test_written_files_follow_the_umask(tmp_path):
    from endowave_cl.atomic import write_bytes_atomic
    from endowave_cl.atomic import atomic_directory
    old = os.umask(0o022)
    try:
        write_bytes_atomic(tmp_path / "a.json", b"{}")
        with atomic_directory(tmp_path / "d") as d:
            (d / "x").write_text("x")
        os.umask(0o077)
        write_bytes_atomic(tmp_path / "b.json", b"{}")
    finally:
        os.umask(old)
    assert (tmp_path / "a.json").stat().st_mode & 0o777 == 0o644       # mkstemp alone gives 0600
    assert (tmp_path / "d").stat().st_mode & 0o777 == 0o755
    assert (tmp_path / "b.json").stat().st_mode & 0o777 == 0o600


def test_json_files_are_strict_json():
    from endowave_cl.atomic import json_safe
    text = json.dumps(json_safe({"psnr": float("inf"), "h": [np.float32("nan"), 1.5]}), allow_nan=False)
    assert json.loads(text) == {"psnr": None, "h": [None, 1.5]}


# ------------------------------------------------------------------ signals
def test_sigterm_saves_and_says_so_in_one_line(tiny_scene, tmp_path):
    run = tmp_path / "run"
    p = subprocess.Popen([sys.executable, "-m", "endowave_cl", "train", str(tiny_scene), "--out", str(run),
                          "--iterations", "100000", "--no-flow", "--set", "init_points=300",
                          "--set", "log_every=10"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 300
    while time.time() < deadline and not (run / "config.json").exists():   # training has started
        time.sleep(0.2)
    time.sleep(1.0)
    p.send_signal(signal.SIGTERM)
    out, err = p.communicate(timeout=300)
    assert p.returncode == 143, err
    last = err.strip().splitlines()[-1]
    assert "stopped by SIGTERM at step" in last and "Traceback" not in err
    step = int(last.split("at step ")[1].split(";")[0])
    assert _steps(run) == [step]
    assert not (run / ".lock").exists()


# ------------------------------------------------------------------ divergence guard
@pytest.mark.parametrize("key,value,what", [
    ("lr_scales", "1e3", "NaN or infinite"),
    ("lr_position_init", "1e3", "ran away"),
    ("lr_time", "1e3", "ran away"),
    ("lr_features", "1e3", "PSNR collapsed"),
])
def test_divergence_stops_the_run_and_keeps_the_good_checkpoint(rt, tiny_scene, tmp_path, key, value, what):
    from endowave_cl.checkpoint import load_checkpoint
    run = tmp_path / "run"
    r = _cli("train", str(tiny_scene), "--out", str(run), "--iterations", "10", "--quiet", "--no-flow",
             "--set", "init_points=500", "--set", "checkpoint_every=5")
    assert r.returncode == 0, r.stderr
    r = _cli("train", str(tiny_scene), "--out", str(run), "--iterations", "60", "--quiet", "--no-flow",
             "--set", "init_points=500", "--set", "checkpoint_every=5", "--set", "log_every=5",
             "--set", "densify_from=20", "--set", "densify_every=20", "--set", f"{key}={value}")
    err = _one_line_error(r, what, "stopped, the last good checkpoint is")
    named = err.split("the last good checkpoint is ")[1].strip()
    assert os.path.isfile(named)                 # the checkpoint it points to was not pruned
    for p in run.glob("checkpoint_*.npz"):      # and whatever was kept is finite
        g = load_checkpoint(p)["gaussians"]
        assert all(np.isfinite(getattr(g, n)).all() for n in ("means", "scales", "sh", "opacity"))
    assert "stopped" in json.loads((run / "train_log.json").read_text())


def test_guard_catches_an_empty_model(rt):
    from endowave_cl.gaussians import Gaussians, upload
    from endowave_cl.train.guard import DivergenceGuard, TrainingDiverged
    guard = DivergenceGuard(1.0, np.zeros(3))
    with pytest.raises(TrainingDiverged, match="every Gaussian was pruned"):
        guard.check(7, upload(rt, Gaussians.empty()), rt)
    g = Gaussians.random(50, seed=1)
    guard.check(7, upload(rt, g), rt)              # a healthy model passes
    guard.observe(1, 20.0)
    guard.reset_reference(2)                        # an opacity reset: the dip is not a collapse
    guard.observe(50, 5.0)
    with pytest.raises(TrainingDiverged, match="collapsed"):
        guard.observe(300, 20.0) or guard.observe(301, 5.0)
