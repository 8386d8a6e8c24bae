"""Issue 57, the second hostile-user sweep: each test here reproduced a defect before its fix
(tools/sweep_cli.py runs the wider sweep these came from).  Tiny scenes, a few steps."""
from __future__ import annotations

import contextlib
import io
import os
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
    for delay in (0.08, 0.15, 0.25, 0.35):
        p = subprocess.Popen([sys.executable, "-m", "endowave_cl", "eval", str(tmp_path / "norun")],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        time.sleep(delay)
        p.send_signal(sig)
        _, err = p.communicate(timeout=60)
        assert "Traceback" not in err, (delay, err)
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
