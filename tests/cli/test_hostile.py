"""Issue 57, the second hostile-user sweep: each test here reproduced a defect before its fix
(tools/sweep_cli.py runs the wider sweep these came from).  Tiny scenes, a few steps."""
from __future__ import annotations

import contextlib
import io
import os
import re
import signal
import subprocess
import sys
import time

import pytest

from endowave_cl import cli


def _main(*argv):
    """(rc, stdout, stderr) of cli.main in this process."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli.main([str(a) for a in argv])
    return rc, out.getvalue(), err.getvalue()


def _one_line(rc, err, *words):
    assert rc == 1, (rc, err)
    lines = err.strip().splitlines()
    assert "Traceback" not in err and len(lines) == 1, err
    assert "unexpected" not in err, err
    for w in words:
        assert w in err, (w, err)
    return lines[0]


# ------------------------------------------------------------------ ENDOWAVE_* variables (item 14)
@pytest.mark.parametrize("name,value", [
    ("ENDOWAVE_RASTER_VW", "junk"), ("ENDOWAVE_RASTER_VW", "3"), ("ENDOWAVE_PROJECT_VW", "x"),
    ("ENDOWAVE_PROGRESS_INTERVAL", "soon"), ("ENDOWAVE_PROGRESS_INTERVAL", "-1"),
    ("ENDOWAVE_PROGRESS_INTERVAL", "nan"), ("ENDOWAVE_RASTER_VARIANT", "fast"),
    ("ENDOWAVE_PROJECT_VARIANT", "1"), ("ENDOWAVE_RASTER_BW", "3"), ("ENDOWAVE_PROGRESS", "loud"),
    ("ENDOWAVE_PROBE_TIMEOUT", "0"), ("ENDOWAVE_PROBE_PLANT", "16=explode"), ("ENDOWAVE_NO_SELECT", "maybe"),
    ("ENDOWAVE_OCLGRIND", "2"), ("ENDOWAVE_CL_NO_DISK_CACHE", "please"),
])
def test_junk_environment_variable_is_named_before_any_work(monkeypatch, tmp_path, name, value):
    monkeypatch.setenv(name, value)
    rc, out, err = _main("export", tmp_path / "norun")      # would fail later for another reason
    _one_line(rc, err, name, repr(value))


def test_every_variable_is_parsed_in_env_py():
    """No module reads an ENDOWAVE_* variable from os.environ itself."""
    import re
    from pathlib import Path
    import endowave_cl
    root = Path(endowave_cl.__file__).parent
    offenders = []
    for p in root.rglob("*.py"):
        if p.name == "env.py":
            continue
        for i, line in enumerate(p.read_text().splitlines(), 1):
            if re.search(r"environ(\.get)?\s*[\(\[]\s*(\"ENDOWAVE_|ENV_)", line) or \
                    re.search(r"getenv\(\s*(\"ENDOWAVE_|ENV_)", line):
                offenders.append(f"{p.relative_to(root)}:{i}: {line.strip()}")
    assert not offenders, offenders


def test_env_values_parse():
    from endowave_cl import env
    os.environ.pop("ENDOWAVE_RASTER_VW", None)
    assert env.get("ENDOWAVE_RASTER_VW") is None
    assert env.PARSERS["ENDOWAVE_RASTER_VW"]("ENDOWAVE_RASTER_VW", " 8 ") == 8
    assert env.PARSERS["ENDOWAVE_PROBE_PLANT"]("ENDOWAVE_PROBE_PLANT", "16=abort, 8=hang") == {16: "abort", 8: "hang"}
    assert env.PARSERS["ENDOWAVE_NO_SELECT"]("ENDOWAVE_NO_SELECT", "Yes") is True


# ------------------------------------------------------------------ Ctrl-C at start-up (item 15)
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_during_startup_is_one_line(tmp_path, sig):
    """A signal in the first fraction of a second (imports, argument parsing): one line, 130 / 143.
    (Not before ~0.06 s: that is the interpreter's own start-up, before endowave-cl runs.)"""
    code = 130 if sig == signal.SIGINT else 143
    t0 = time.perf_counter()                 # the interpreter's own start-up on this machine, now
    subprocess.run([sys.executable, "-c", "pass"], check=True)
    start = time.perf_counter() - t0
    for delay in (0.02, 0.1, 0.2, 0.3):
        p = subprocess.Popen([sys.executable, "-m", "endowave_cl", "eval", str(tmp_path / "norun")],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        time.sleep(start + delay)
        p.send_signal(sig)
        _, err = p.communicate(timeout=60)
        if "Traceback" in err and not re.search(r'cli\.py", line \d+, in (main|_run|build_parser)', err):
            continue     # before cli.main ran: the interpreter's start-up or importing cli.py (~10 ms)
        assert "Traceback" not in err and "Exception ignored" not in err, (delay, err)
        if p.returncode in (code, 1):    # 1: it had already finished with its error
            assert len(err.strip().splitlines()) <= 1, err
        else:
            assert p.returncode == -sig, (delay, p.returncode, err)


# ------------------------------------------------------------------ data loss (items 1, 2, 5)
def _fake_run(run, step=3):
    import json
    run.mkdir(parents=True, exist_ok=True)
    (run / f"checkpoint_{step:07d}.npz").write_bytes(b"model")
    (run / "config.json").write_text(json.dumps({"scene": "s", "iterations": 3}))
    (run / "train_log.json").write_text(json.dumps({"final": None, "history": [{"step": step}]}))


def test_restart_killed_before_its_first_checkpoint_keeps_previous_run(tmp_path):
    """train --restart twice, the first killed before its first checkpoint (batch --force alike)."""
    import json
    from endowave_cl.train.run_folder import retire_previous_run
    run = tmp_path / "run"
    _fake_run(run)
    logs = []
    assert retire_previous_run(run, logs.append) == run / "previous_run"
    (run / "config.json").write_text(json.dumps({"scene": "s", "iterations": 5}))   # start() of run 2, then killed
    retire_previous_run(run, logs.append)                                          # run 3 --restart
    prev = run / "previous_run"
    assert (prev / "checkpoint_0000003.npz").read_bytes() == b"model"
    assert json.loads((prev / "config.json").read_text())["iterations"] == 3
    assert (prev / "train_log.json").is_file()
    assert not (run / "config.json").exists()
    # a run that did save a model does replace previous_run/
    _fake_run(run, step=7)
    retire_previous_run(run, logs.append)
    assert (prev / "checkpoint_0000007.npz").is_file() and not (prev / "checkpoint_0000003.npz").exists()


@pytest.mark.parametrize("name,text", [("config.json", '{"lr": 1}'), ("config.json", "not json"),
                                       ("train_log.json", "[1, 2]")])
def test_out_folder_with_a_users_config_is_refused(tmp_path, name, text):
    from endowave_cl.errors import EndowaveError
    from endowave_cl.train.run_folder import RunSession
    d = tmp_path / "mine"
    d.mkdir()
    (d / name).write_text(text)
    with pytest.raises(EndowaveError, match=f"{name}: this file is not an endowave-cl run's"):
        RunSession(d, log=lambda m: None)
    assert (d / name).read_text() == text and sorted(p.name for p in d.iterdir()) == [name]


def test_all_checkpoints_unreadable_does_not_start_over_silently(tmp_path):
    from endowave_cl.errors import EndowaveError
    from endowave_cl.train.run_folder import RunSession
    run = tmp_path / "run"
    _fake_run(run)
    s = RunSession(run, log=lambda m: None)
    with pytest.raises(EndowaveError, match="not a readable checkpoint"):     # the first train: set aside
        s.resume_point(None)
    s.abort()
    assert (run / "checkpoint_0000003.npz.corrupt").is_file()
    s = RunSession(run, log=lambda m: None)
    with pytest.raises(EndowaveError, match="no readable checkpoint to resume from.*--restart"):
        s.resume_point(None)                                                   # the same command again
    s.abort()
    (run / "checkpoint_0000003.npz.corrupt").unlink()                          # removed by hand: the log is there
    s = RunSession(run, log=lambda m: None)
    with pytest.raises(EndowaveError, match="train_log.json: this run logged training steps"):
        s.resume_point(None)
    s.abort()
    assert "history" in (run / "train_log.json").read_text()


# ------------------------------------------------------------------ a run opened on another scene (item 3)
@pytest.fixture(scope="module")
def own_run(tmp_path_factory):
    """(scene, run): a tiny scene of this module's own (tests regenerate it) and a 2-step run on it."""
    from endowave_cl.data.synth import make_synthetic_scene
    root = tmp_path_factory.mktemp("own")
    make_synthetic_scene(root / "scene", width=48, height=32, frames=10, seed=3)
    rc, _, err = _main("train", root / "scene", "--out", root / "run", "--iterations", "2", "--quiet", "--no-flow",
                       "--set", "init_points=100")
    assert rc == 0, err
    return root / "scene", root / "run"


def test_eval_render_view_on_another_scene_are_refused(own_run, tmp_path):
    from endowave_cl.data.synth import make_synthetic_scene
    from endowave_cl.errors import EndowaveError
    from endowave_cl.run_io import load_run
    scene, run = own_run
    other = tmp_path / "other"
    make_synthetic_scene(other, width=48, height=32, frames=10, seed=4)
    before = sorted(p.name for p in run.iterdir())
    for cmd in (["eval", run, "--scene", other, "--fps-runs", "0"], ["render", run, "--scene", other, "--no-video"]):
        rc, _, err = _main(*cmd)
        _one_line(rc, err, "is not that scene", "its frames differ")
    with pytest.raises(EndowaveError, match="is not that scene"):   # view opens the run with load_run
        load_run(run, str(other))
    assert sorted(p.name for p in run.iterdir()) == before           # no eval.json, no render/
    assert load_run(run).step == 2


def test_scene_regenerated_in_place_is_refused_by_eval_and_export(own_run, tmp_path):
    import shutil
    from endowave_cl.data.synth import make_synthetic_scene
    scene, run = own_run
    keep = tmp_path / "keep"
    shutil.copytree(scene, keep)
    try:
        make_synthetic_scene(scene, width=48, height=32, frames=10, seed=9, force=True)
        for cmd in (["eval", run, "--fps-runs", "0", "--no-baselines"], ["export", run, "--out", tmp_path / "m.ply"]):
            rc, _, err = _main(*cmd)
            _one_line(rc, err, "is not that scene")
        assert not (tmp_path / "m.ply").exists()
    finally:
        shutil.rmtree(scene)
        shutil.copytree(keep, scene)
    rc, _, err = _main("export", run, "--out", tmp_path / "m.ply")
    assert rc == 0 and (tmp_path / "m.ply").is_file(), err


# ------------------------------------------------------------------ flow: cache, sizes, user flow (items 11, 12, 16, 17, 20)
@pytest.fixture(scope="module")
def flow_scene(tmp_path_factory):
    from endowave_cl.data.synth import make_synthetic_scene
    out = tmp_path_factory.mktemp("flow") / "scene"
    make_synthetic_scene(out, width=64, height=48, frames=6, seed=2)
    return out


def test_damaged_flow_cache_file_is_named_and_recomputed(flow_scene, tmp_path, capsys):
    import numpy as np
    from endowave_cl.data import flow_for_scene, load_scene
    scene = load_scene(flow_scene)
    first = flow_for_scene(scene, progress=False, cache_dir=tmp_path)
    files = sorted(first.cache_path.glob("*.npz"))
    data = files[0].read_bytes()
    for damage in (data[: len(data) // 2], data[:100] + bytes([data[100] ^ 0xFF]) + data[101:]):
        files[0].write_bytes(damage)
        again = flow_for_scene(scene, progress=False, cache_dir=tmp_path)
        assert again.computed, "a damaged entry must be recomputed"
        err = capsys.readouterr().err
        assert files[0].name in err and "damaged" in err, err
        np.testing.assert_array_equal(again[0].flow, first[0].flow)
    assert not flow_for_scene(scene, progress=False, cache_dir=tmp_path).computed   # replaced: a hit again


def test_flow_cache_that_cannot_be_written_is_named_and_skipped(flow_scene, tmp_path, monkeypatch, capsys):
    import errno
    import numpy as np
    from endowave_cl.data import flow_for_scene, load_scene

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(np, "savez", full)
    res = flow_for_scene(load_scene(flow_scene), progress=False, cache_dir=tmp_path / "c")
    assert res.computed and res.cache_path is None and len(res) > 0
    err = capsys.readouterr().err
    assert str(tmp_path / "c") in err and "No space left on device" in err, err


def test_flow_max_pixels_too_small_is_refused_up_front(flow_scene, tmp_path):
    rc, _, err = _main("flow", flow_scene, "--max-pixels", "50", "--cache-dir", tmp_path)
    _one_line(rc, err, "--max-pixels", "at least 256")
    rc, _, err = _main("train", flow_scene, "--out", tmp_path / "r", "--set", "flow_max_pixels=20")
    _one_line(rc, err, "flow_max_pixels", "at least 256")
    assert not (tmp_path / "r").exists()
    from endowave_cl.data.flow import estimation_size
    assert min(estimation_size(640, 480, 300)) >= 16


def test_full_size_user_flow_and_gt_flow_at_an_uneven_downscale(flow_scene, tmp_path):
    """--downscale 2.5 on 64x48 gives 26x19 (ratios 0.406 / 0.396): full-size flow is what the docs
    ask for and must fit; a gt_flow file that cannot be used fails train before any step."""
    import shutil
    import numpy as np
    from endowave_cl.data import flow_for_scene, load_scene
    from endowave_cl.data.flow import _fit_to_scene
    scene = load_scene(flow_scene, downscale=2.5)
    assert (scene.width, scene.height) == (26, 19)
    fit = _fit_to_scene(np.ones((48, 64, 2), np.float32), "f.npy", scene)
    assert fit.shape == (19, 26, 2)
    s2 = tmp_path / "s"
    shutil.copytree(flow_scene, s2)
    np.save(s2 / "gt_flow" / "000001.npy", np.zeros((10, 10, 2), np.float32))
    t0 = time.perf_counter()
    rc, out, err = _main("train", s2, "--out", tmp_path / "r", "--iterations", "50", "--quiet", "--no-flow")
    _one_line(rc, err, "000001.npy", "does not scale")
    assert "training" not in out and time.perf_counter() - t0 < 60
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("value", [1e30, -3e6, float("nan")])
def test_user_flow_with_absurd_vectors_is_named(flow_scene, tmp_path, value):
    import shutil
    import numpy as np
    from endowave_cl.data import flow_for_scene, load_scene
    from endowave_cl.errors import DataError
    s2 = tmp_path / "s"
    shutil.copytree(flow_scene, s2)
    scene = load_scene(s2)
    (s2 / "flow").mkdir()
    names = [f.name for f in scene.frames]
    for k, k2 in zip(scene.train_indices[:-1], scene.train_indices[1:]):
        np.save(s2 / "flow" / f"{names[k]}_{names[k2]}.npy", np.zeros((48, 64, 2), np.float32))
    bad = s2 / "flow" / f"{names[scene.train_indices[0]]}_{names[scene.train_indices[1]]}.npy"
    np.save(bad, np.full((48, 64, 2), value, np.float32))
    with pytest.raises(DataError, match=bad.name):
        flow_for_scene(load_scene(s2), progress=False)


# ------------------------------------------------------------------ scene folders (items 4, 10, 13, 18, 19)
def test_unpadded_frame_numbers_load_in_numeric_order(tmp_path):
    import numpy as np
    from endowave_cl.data import load_scene
    from endowave_cl.data.images import list_images
    from endowave_cl.data.synth import make_synthetic_scene
    s = tmp_path / "s"
    make_synthetic_scene(s, width=32, height=24, frames=12, seed=1)
    ref = load_scene(s)
    for sub in ("images", "depth", "masks"):
        for p in (s / sub).glob("*.png"):
            p.rename(p.with_name(f"{int(p.stem)}.png"))          # 0.png ... 11.png
    got = load_scene(s)
    assert [f.name for f in got.frames] == [str(i) for i in range(12)]
    for a, b in zip(ref.frames, got.frames):
        np.testing.assert_array_equal(a.image, b.image)
    assert [p.name for p in list_images(s / "images")][:4] == ["0.png", "1.png", "2.png", "3.png"]


def _scene_copy(flow_scene, tmp_path, masks_all_tool=(), depth=True, depth_scale=None):
    import json
    import shutil
    import cv2
    import numpy as np
    s = tmp_path / "s"
    shutil.copytree(flow_scene, s)
    files = sorted((s / "masks").glob("*.png"))
    for i in masks_all_tool:
        cv2.imwrite(str(files[i]), np.full((48, 64), 255, np.uint8))       # 255 = tool
    if not depth:
        shutil.rmtree(s / "depth")
    if depth_scale is not None:
        info = json.loads((s / "scene.json").read_text())
        info["depth_scale"] = depth_scale
        (s / "scene.json").write_text(json.dumps(info))
    return s


@pytest.mark.parametrize("tool,depth,words", [
    ((1,), True, ["masks/000001.png", "test frame 1 is all tool"]),
    (tuple(range(6)), False, ["test frame 1 is all tool"]),
    ((0, 2, 3, 4, 5), False, ["every training frame's mask is all tool"]),
])
def test_all_tool_masks_are_refused_before_training(flow_scene, tmp_path, tool, depth, words):
    s = _scene_copy(flow_scene, tmp_path, tool, depth)
    rc, out, err = _main("train", s, "--out", tmp_path / "r", "--iterations", "50", "--quiet", "--no-flow")
    line = _one_line(rc, err, *words)
    assert "depth" not in line.replace("depth/", "")
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("value", [1e-300, 1e300, float("inf"), True, -1, 0, "2"])
def test_depth_scale_out_of_range_is_named(flow_scene, tmp_path, value):
    s = _scene_copy(flow_scene, tmp_path, depth_scale=value)
    rc, out, err = _main("train", s, "--out", tmp_path / "r", "--iterations", "50", "--quiet")
    _one_line(rc, err, "scene.json", "depth_scale")


def test_init_blames_masks_not_depth_without_depth():
    import numpy as np
    from types import SimpleNamespace
    from endowave_cl.errors import EndowaveError
    from endowave_cl.train.init import init_gaussians
    from endowave_cl.camera import Camera
    cam = Camera(40.0, 40.0, 16.0, 12.0, 32, 24, np.eye(4))
    fr = SimpleNamespace(image=np.zeros((24, 32, 3), np.float32), depth=None, mask=np.zeros((24, 32), np.float32),
                         camera=cam, time=0.0)
    with pytest.raises(EndowaveError, match="no training pixel is tissue"):
        init_gaussians([fr, fr], [0, 1], 1.0, 10.0, 100)


# ------------------------------------------------------------------ synth (items 7, 22)
@pytest.mark.parametrize("args,words", [
    (["--deformation", "inf"], ["--deformation", "got inf"]),
    (["--deformation", "nan"], ["--deformation"]),
    (["--deformation", "-1"], ["--deformation"]),
    (["--deformation", "10", "--width", "32", "--height", "24", "--frames", "4"], ["--deformation 10", "smaller"]),
    (["--seed", "-1"], ["--seed", "got -1"]),
    (["--width", "100000"], ["too large"]),
    (["--frames", "1"], ["--frames"]),
])
def test_synth_parameters_are_named_and_nothing_is_left(tmp_path, args, words):
    t0 = time.perf_counter()
    rc, _, err = _main("synth", tmp_path / "out", *args)
    line = _one_line(rc, err, *words)
    assert str(tmp_path / "out") not in line
    assert time.perf_counter() - t0 < 30
    assert list(tmp_path.iterdir()) == []                       # no folder, no hidden temporary


def test_synth_removes_a_killed_writers_temporary(tmp_path):
    stale = tmp_path / ".out.999999999.abc.tmp"                 # pid that cannot exist
    stale.mkdir()
    (stale / "images").mkdir()
    rc, _, err = _main("synth", tmp_path / "out", "--width", "32", "--height", "24", "--frames", "3")
    assert rc == 0, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


# ------------------------------------------------------------------ render (item 21)
@pytest.mark.parametrize("fps", ["1e-9", "1e9", "0.01"])
def test_render_fps_the_encoders_cannot_write_is_refused_up_front(own_run, fps):
    scene, run = own_run
    rc, out, err = _main("render", run, "--fps", fps)
    _one_line(rc, err, "--fps must be from 0.1 to 1000")
    assert "render:" not in out


def test_render_video_failure_is_one_warning_line(own_run, monkeypatch):
    from endowave_cl.commands import render

    def broken(path, frames, fps, codec=None):
        raise OSError("FFMPEG STDERR OUTPUT:\nboom: cannot encode\nmore noise")
    monkeypatch.setattr(render, "write_video", broken)     # video.write_video as the command imports it
    scene, run = own_run
    rc, out, err = _main("render", run, "--fps", "5")
    assert rc == 0 and err.strip() == "warning: video not written (boom: cannot encode); the frames are written as PNG"


# ------------------------------------------------------------------ batch (items 6, 8, 9)
@pytest.mark.parametrize("text,words", [
    ("[resources]\ncpus = 1e300", ["resources.cpus", "to 1024"]),
    ("[resources]\ncpus = 100000", ["resources.cpus"]),
    ("[render]\nfps = 1e9", ["render.fps", "from 0.1 to 1000"]),
])
def test_manifest_resources_out_of_range(tmp_path, text, words):
    from endowave_cl.batch.manifest import load_manifest
    from endowave_cl.errors import EndowaveError
    (tmp_path / "data" / "a").mkdir(parents=True)
    p = tmp_path / "m.toml"
    p.write_text('root = "o"\nscenes = ["data/*"]\n' + text)
    with pytest.raises(EndowaveError) as e:
        load_manifest(p)
    for w in words:
        assert w in str(e.value) and str(p) in str(e.value)


def test_task_threads_are_bounded():
    from types import SimpleNamespace
    from endowave_cl.batch.tasks import task_env
    env = task_env(SimpleNamespace(resources={"cpus": 1e300}))
    assert all(int(env[v]) <= 1024 for v in ("POCL_MAX_PTHREAD_COUNT", "OMP_NUM_THREADS") if v not in os.environ)


def test_a_locked_run_folder_is_not_a_sticky_data_error(tmp_path):
    from endowave_cl.batch import tasks
    from endowave_cl.train.run_folder import RunLock
    run = tmp_path / "run"
    run.mkdir()
    lock = RunLock(run).acquire()           # an orphaned worker still training
    try:
        res = tasks._retire(run)
        assert res["kind"] == tasks.BUSY_KIND and "in use" in res["error"]
        res = tasks._run_command(["export", str(run)])       # opens no lock: a data error as before
        assert res["kind"] == "data"
    finally:
        lock.release()
    assert tasks.BUSY_KIND not in tasks.STICKY_KINDS


def test_pool_worker_dies_with_its_driver(tmp_path):
    """SIGKILL of the driver: its worker notices the new parent and stops (SIGTERM, then exit)."""
    code = ("import subprocess, sys, time\n"
            "w = subprocess.Popen([sys.executable, '-c', 'import os, time; from endowave_cl.batch.tasks import "
            "_die_with_parent; _die_with_parent(os.getppid()); print(os.getpid(), flush=True); time.sleep(120)'],"
            " stdout=subprocess.PIPE, text=True)\n"
            "print(w.stdout.readline().strip(), flush=True)\n"
            "time.sleep(120)\n")
    driver = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    worker = int(driver.stdout.readline())
    driver.kill()
    driver.wait()
    deadline = time.time() + 20
    while time.time() < deadline:
        try:
            with open(f"/proc/{worker}/stat") as f:
                if f.read().rsplit(")", 1)[1].split()[0] == "Z":    # exited; its new parent has not reaped it
                    break
        except (FileNotFoundError, ProcessLookupError):
            break
        time.sleep(0.2)
    else:
        os.kill(worker, signal.SIGKILL)
        pytest.fail("the worker outlived its driver by 20 s")


# ------------------------------------------------------------------ found by tools/sweep_cli.py
def test_manifest_cpus_tiny_is_refused(tmp_path):
    from endowave_cl.batch.manifest import load_manifest
    from endowave_cl.errors import EndowaveError
    (tmp_path / "data" / "a").mkdir(parents=True)
    p = tmp_path / "m.toml"
    p.write_text('root = "o"\nscenes = ["data/*"]\n[resources]\ncpus = 1e-300\n')
    with pytest.raises(EndowaveError, match="resources.cpus' must be from 0.01"):
        load_manifest(p)


def test_flow_command_refuses_absurd_gt_flow(flow_scene, tmp_path):
    import shutil
    import numpy as np
    s = tmp_path / "s"
    shutil.copytree(flow_scene, s)
    np.save(s / "gt_flow" / "000002.npy", np.full((48, 64, 2), 1e30, np.float32))
    rc, out, err = _main("flow", s, "--cache-dir", tmp_path / "c", "--no-progress")
    _one_line(rc, err, "000002.npy", "flow vectors up to")


def test_eval_fps_runs_without_end_is_refused(own_run):
    scene, run = own_run
    rc, _, err = _main("eval", run, "--fps-runs", "99999999999999999999")
    _one_line(rc, err, "--fps-runs must be at most 10000")
