"""One-line errors instead of tracebacks or silent acceptance (issue #14): config ranges, command
line values, run folder and output paths."""
from __future__ import annotations

import shutil
import subprocess
import sys

import pytest

from endowave_cl.errors import EndowaveError
from endowave_cl.train.config import RANGES, TrainConfig, load_config, validate_config


def _cli(*args, **kw):
    return subprocess.run([sys.executable, "-m", "endowave_cl", *args], capture_output=True, text=True,
                          timeout=600, **kw)


def _one_line_error(r, *words):
    err = r.stderr.strip()
    assert r.returncode == 1, (r.returncode, r.stdout, r.stderr)
    assert "Traceback" not in r.stderr and len(err.splitlines()) == 1, r.stderr
    for w in words:
        assert w in err, (w, err)
    return err


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    from endowave_cl.data.synth import make_synthetic_scene
    out = tmp_path_factory.mktemp("scene") / "tiny"
    make_synthetic_scene(out, seed=3, width=64, height=48, frames=10)
    return out


# ------------------------------------------------------------------ config ranges
def test_defaults_validate_and_every_numeric_key_has_a_range():
    validate_config(TrainConfig(), "defaults")
    numeric = {k for k, v in TrainConfig().to_dict().items() if type(v) in (int, float)}
    assert numeric - set(RANGES) == {"sh_degree", "temporal_freqs"}   # those two are fixed values


@pytest.mark.parametrize("key,value,words", [
    ("lr_scales", "nan", "is NaN"),
    ("lr_opacity", "-0.05", "must be at least 0"),
    ("lr_position_init", "inf", "must be finite"),
    ("seed", "-1", "must be in [0"),
    ("log_every", "0", "must be at least 1"),
    ("iterations", "0", "must be at least 1"),
    ("downscale", "inf", "must be finite"),
    ("downscale", "0.5", "must be at least 1"),
    ("init_points", "-1", "must be at least 0"),
    ("lambda_dssim", "1.5", "must be in [0, 1]"),
    ("opacity_reset_value", "0", "must be in (0, 1)"),
    ("sh_degree", "2", "must be 3"),
    ("temporal_freqs", "5", "must be 2"),
    ("flow_method", "bogus", "must be one of dis"),
])
def test_bad_values_name_the_key(key, value, words):
    with pytest.raises(EndowaveError, match=None) as e:
        load_config(None, {key: value})
    assert f"override: key '{key}'" in str(e.value) and words in str(e.value), str(e.value)


def test_config_path_that_is_a_folder(tmp_path):
    with pytest.raises(EndowaveError, match="is a folder, not a TOML config file"):
        load_config(str(tmp_path))


# ------------------------------------------------------------------ the command line
@pytest.mark.parametrize("args,words", [
    (["--iterations", "0"], ["--iterations must be at least 1, got 0"]),
    (["--iterations", "-5"], ["--iterations must be at least 1"]),
    (["--downscale", "inf"], ["--downscale must be a finite number >= 1"]),
    (["--downscale", "1000"], ["downscale 1000 leaves 0x0 pixels", "images"]),
    (["--set", "seed=-1"], ["key 'seed'"]),
    (["--set", "log_every=0"], ["key 'log_every'"]),
    (["--set", "lr_scales=nan"], ["key 'lr_scales' is NaN"]),
    (["--set", "sh_degree=1"], ["key 'sh_degree' must be 3"]),
])
def test_train_rejects_bad_values_before_touching_the_run_folder(tiny_scene, tmp_path, args, words):
    run = tmp_path / "run"
    r = _cli("train", str(tiny_scene), "--out", str(run), "--quiet", *args)
    _one_line_error(r, *words)
    assert not run.exists()


def test_bad_out_and_config_paths(tiny_scene, tmp_path):
    f = tmp_path / "afile"
    f.write_text("x")
    _one_line_error(_cli("train", str(tiny_scene), "--out", str(f), "--quiet"), "afile", "not a folder")
    _one_line_error(_cli("train", str(tiny_scene), "--out", str(f / "run"), "--quiet", "--iterations", "1"),
                    "afile is a file")
    _one_line_error(_cli("train", str(tiny_scene), "--out", str(tmp_path / "r"), "--config", str(tmp_path)),
                    "is a folder, not a TOML config file")
    # read-only even for root: /sys refuses new folders
    _one_line_error(_cli("train", str(tiny_scene), "--out", "/sys/endowave_run", "--quiet",
                         "--iterations", "1", "--no-flow", "--set", "init_points=100"), "/sys/endowave_run")


def test_one_frame_scene_is_refused(tiny_scene, tmp_path):
    import numpy as np
    one = tmp_path / "one"
    one.mkdir()
    for sub in ("images", "depth", "masks"):
        (one / sub).mkdir()
        first = sorted((tiny_scene / sub).glob("*.png"))[0]
        shutil.copy(first, one / sub / first.name)
    np.save(one / "poses_bounds.npy", np.load(tiny_scene / "poses_bounds.npy")[:1])
    shutil.copy(tiny_scene / "scene.json", one / "scene.json")
    _one_line_error(_cli("train", str(one), "--out", str(tmp_path / "run"), "--quiet"),
                    "1 frame(s)", "at least 2 frames")


def test_render_export_bad_arguments(tiny_scene, tmp_path):
    run = tmp_path / "run"
    r = _cli("train", str(tiny_scene), "--out", str(run), "--iterations", "2", "--quiet", "--no-flow",
             "--set", "init_points=200")
    assert r.returncode == 0, r.stderr
    _one_line_error(_cli("render", str(run), "--fps", "0"), "--fps must be a positive number")
    (tmp_path / "adir").mkdir()
    _one_line_error(_cli("export", str(run), "--out", str(tmp_path / "adir")), "adir: is a folder")
    _one_line_error(_cli("export", str(tmp_path / "norun")), "norun: run folder not found")


def test_unexpected_exception_is_one_line(monkeypatch, capsys):
    from endowave_cl import cli
    from endowave_cl.commands import export

    def boom(args):
        raise ZeroDivisionError("division by zero")
    monkeypatch.setattr(export, "run", boom)
    monkeypatch.delenv("ENDOWAVE_CL_DEBUG", raising=False)
    assert cli.main(["export", "somewhere"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("endowave-cl export: error: unexpected ZeroDivisionError") and len(err.splitlines()) == 1
