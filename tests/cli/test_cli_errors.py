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


# ------------------------------------------------------------------ config ranges
def test_defaults_validate_and_every_numeric_key_has_a_range():
    validate_config(TrainConfig(), "defaults")
    numeric = {k for k, v in TrainConfig().to_dict().items() if type(v) in (int, float)}
    assert numeric - set(RANGES) == {"temporal_freqs"}   # a fixed value


@pytest.mark.parametrize("key,value,words", [
    ("lr_scales", "nan", "is NaN"),
    ("lr_opacity", "-0.05", "must be at least 0"),
    ("lr_position_init", "inf", "must be finite"),
    ("seed", "-1", "must be in [0"),
    ("log_every", "0", "must be at least 1"),
    ("iterations", "-1", "must be at least 0"),
    ("downscale", "inf", "must be finite"),
    ("downscale", "0.5", "must be at least 1"),
    ("init_points", "-1", "must be at least 0"),
    ("lambda_dssim", "1.5", "must be in [0, 1]"),
    ("opacity_reset_value", "0", "must be in (0, 1)"),
    ("sh_degree", "4", "must be in [-1, 3]"),
    ("temporal_freqs", "5", "must be 2"),
    ("flow_method", "bogus", "must be one of dis"),
    ("wavelet_q", "0", "must be at least 1"),
    ("wavelet_levels", "1.5", "expects int"),
    ("wavelet_weight_hh", "-1", "must be at least 0"),
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
    (["--set", "sh_degree=-2"], ["key 'sh_degree' must be in [-1, 3]"]),
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


@pytest.fixture(scope="module")
def tiny_run(tiny_scene, tmp_path_factory):
    run = tmp_path_factory.mktemp("runs") / "run"
    r = _cli("train", str(tiny_scene), "--out", str(run), "--iterations", "2", "--quiet", "--no-flow",
             "--set", "init_points=200")
    assert r.returncode == 0, r.stderr
    return run


def test_render_export_bad_arguments(tiny_run, tmp_path):
    run = tiny_run
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


# ------------------------------------------------------------------ poses, image sizes, eval
def _scene_copy(tiny_scene, tmp_path):
    d = tmp_path / "scene"
    shutil.copytree(tiny_scene, d)
    return d


@pytest.mark.parametrize("damage,words", [
    ("zero", ["poses_bounds.npy (row 4)", "not orthonormal"]),
    ("singular", ["poses_bounds.npy (row 4)", "not orthonormal"]),
    ("tiny", ["poses_bounds.npy (row 4)", "not orthonormal"]),
    ("mirror", ["poses_bounds.npy (row 4)", "determinant -1"]),
    ("text", ["poses_bounds.npy", "row 4 holds 'x1'"]),
])
def test_bad_pose_rows_are_one_line(tiny_scene, tmp_path, damage, words):
    import numpy as np
    scene = _scene_copy(tiny_scene, tmp_path)
    arr = np.load(scene / "poses_bounds.npy")
    R = {"zero": np.zeros((3, 3)), "singular": np.array([[1.0, 0, 0], [0, 1, 0], [0, 1, 0]]),
         "tiny": np.eye(3) * 1e-9, "mirror": np.diag([-1.0, 1, 1]), "text": np.eye(3)}[damage]
    pose = arr[4, :15].reshape(3, 5)
    pose[:, :3] = R
    arr[4, :15] = pose.reshape(-1)
    if damage == "text":
        arr = arr.astype(str)
        arr[4, 0] = "x1"
    np.save(scene / "poses_bounds.npy", arr)
    run = tmp_path / "run"
    _one_line_error(_cli("train", str(scene), "--out", str(run), "--quiet", "--no-flow"), *words)
    assert not run.exists()


def test_odd_first_image_is_named(tiny_scene, tmp_path):
    import cv2
    scene = _scene_copy(tiny_scene, tmp_path)
    first = scene / "images" / "000000.png"
    cv2.imwrite(str(first), cv2.resize(cv2.imread(str(first)), (40, 30)))
    _one_line_error(_cli("train", str(scene), "--out", str(tmp_path / "run"), "--quiet", "--no-flow"),
                    str(first), "size 40x30 disagrees with the 64x48 of the other images")


def test_eval_fps_runs_and_one_frame_scene(tiny_scene, tiny_run, tmp_path):
    import json

    import numpy as np
    _one_line_error(_cli("eval", str(tiny_run), "--fps-runs", "-3"), "--fps-runs must be >= 0, got -3")
    r = _cli("eval", str(tiny_run), "--fps-runs", "0", "--no-baselines")
    assert r.returncode == 0, r.stderr
    assert json.loads((tiny_run / "eval.json").read_text())["fps"] is None
    one = tmp_path / "one"
    for sub in ("images", "depth", "masks"):
        (one / sub).mkdir(parents=True)
        first = sorted((tiny_scene / sub).glob("*.png"))[0]
        shutil.copy(first, one / sub / first.name)
    np.save(one / "poses_bounds.npy", np.load(tiny_scene / "poses_bounds.npy")[:1])
    shutil.copy(tiny_scene / "scene.json", one / "scene.json")
    # another scene than the run's: its fingerprint (10 frames there, 1 here) refuses it first (issue 57)
    _one_line_error(_cli("eval", str(tiny_run), "--scene", str(one)), str(one), "is not that scene",
                    "10 frames there, 1 here")


def test_eval_json_is_strict_when_psnr_is_infinite(tiny_run, monkeypatch, capsys):
    """All-black frames rendered exactly give PSNR inf: eval.json stays strict JSON (null)."""
    import json

    from endowave_cl import cli, evaluation
    real = evaluation.frame_scores

    def exact(pred, gt, mask=None, with_lpips=False):
        out = real(pred, gt, mask, with_lpips)
        out.update(psnr=float("inf"), psnr_masked=float("inf"))
        return out
    monkeypatch.setattr(evaluation, "frame_scores", exact)   # metrics.frame_scores as evaluation imports it
    assert cli.main(["eval", str(tiny_run), "--fps-runs", "0"]) == 0, capsys.readouterr().err
    text = (tiny_run / "eval.json").read_text()

    def refuse(word):
        raise AssertionError(f"eval.json holds {word}")
    m = json.loads(text, parse_constant=refuse)
    assert m["psnr"] is None and m["per_frame"][0]["model"]["psnr"] is None
    assert m["ssim"] is not None
