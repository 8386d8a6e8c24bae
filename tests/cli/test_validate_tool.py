"""tools/validate.py: it prints validation figures only (a run scored on the test frames is refused
unless --test asks for the report), per run, per scene and against motion."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

TOOL = Path(__file__).resolve().parents[2] / "tools" / "validate.py"


def _scores(psnr, lpips=0.05):
    return {"psnr": psnr, "psnr_masked": psnr, "ssim": 0.9, "lpips": lpips}


def _fake_run(folder: Path, split: str, model: float, teacher: float, motion: float):
    folder.mkdir(parents=True)
    per = [{"index": 5, "motion": motion, "model": _scores(model), "teacher": _scores(teacher)}]
    base = {n: _scores(v) for n, v in (("mean", 30.0), ("dis", 33.0), ("dis_cubic", 33.5), ("teacher", teacher))}
    m = {**_scores(model), "split": split, "baselines": base, "step": 100, "per_frame": per,
         "margin": {"over": "teacher", "psnr": model - teacher}, "margin_teacher": {"psnr": model - teacher},
         "train_fit": {"psnr": 40.0, "frames": 5}}
    (folder / "eval.json").write_text(json.dumps(m))
    (folder / "train_log.json").write_text(json.dumps({"final": {"train_seconds": 12.0}}))


def _tool(*args):
    return subprocess.run([sys.executable, str(TOOL), *map(str, args)], capture_output=True, text=True, timeout=120)


def test_summary_of_validation_runs(tmp_path):
    _fake_run(tmp_path / "cand" / "traction_s0", "validation", 35.0, 36.0, 0.3)
    _fake_run(tmp_path / "cand" / "traction_s1", "validation", 36.0, 36.0, 3.0)
    r = _tool("--tag", "cand", "--out", tmp_path, "--scenes", "traction", "--seeds", "0,1", "--summary",
              "--shared", tmp_path / "nowhere")
    assert r.returncode == 1 and "not found, skipped" in r.stdout          # a missing scene is skipped
    (tmp_path / "shared" / "data" / "endonerf_clips" / "traction").mkdir(parents=True)
    r = _tool("--tag", "cand", "--out", tmp_path, "--scenes", "traction", "--seeds", "0,1", "--summary",
              "--shared", tmp_path / "shared")
    assert r.returncode == 0, r.stderr
    assert "validation frames" in r.stdout and "traction (2 seeds): psnr 35.500 +- 0.500" in r.stdout
    assert "margin_teacher -0.500 +- 0.500" in r.stdout
    assert "motion  0.0-0.5  px:   1 frames, margin -1.00 dB" in r.stdout
    assert "motion  2.0-4.0  px:   1 frames, margin +0.00 dB" in r.stdout
    summary = json.loads((tmp_path / "cand" / "summary.json").read_text())
    assert summary["scenes"]["traction"]["fit"] == 40.0


def test_test_frames_are_refused_without_test(tmp_path):
    (tmp_path / "shared" / "data" / "endonerf_clips" / "pushing").mkdir(parents=True)
    _fake_run(tmp_path / "x" / "pushing_s0", "test", 35.0, 36.0, 1.0)
    args = ("--tag", "x", "--out", tmp_path, "--scenes", "pushing", "--summary", "--shared", tmp_path / "shared")
    r = _tool(*args)
    assert r.returncode != 0 and "not the validation frames" in r.stderr and "35.00" not in r.stdout
    r = _tool(*args, "--test")
    assert r.returncode == 0 and "test frames" in r.stdout


def test_summary_covers_every_finished_run_of_the_tag(tmp_path):
    """Two invocations of one tag trained side by side (one scene each) share summary.json: each
    writes the runs of both."""
    for name in ("traction", "pushing"):
        (tmp_path / "shared" / "data" / "endonerf_clips" / name).mkdir(parents=True)
    _fake_run(tmp_path / "cand" / "traction_s0", "validation", 35.0, 36.0, 0.3)
    _fake_run(tmp_path / "cand" / "pushing_s0", "validation", 33.0, 34.0, 3.0)
    r = _tool("--tag", "cand", "--out", tmp_path, "--scenes", "pushing", "--summary", "--shared", tmp_path / "shared")
    assert r.returncode == 0, r.stderr
    summary = json.loads((tmp_path / "cand" / "summary.json").read_text())
    assert sorted(summary["scenes"]) == ["_by_motion", "pushing", "traction"]
    assert [x["scene"] for x in summary["runs"]] == ["traction", "pushing"]


def _load_tool():
    import importlib.util
    spec = importlib.util.spec_from_file_location("validate_tool", TOOL)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_checkpoints_are_deleted_once_scored_unless_kept(tmp_path, monkeypatch):
    """A screen runs hundreds of trainings: their checkpoints go once eval.json is written."""
    tool = _load_tool()
    scene = tmp_path / "shared" / "data" / "endonerf_clips" / "traction"
    scene.mkdir(parents=True)

    def fake_run(cmd, log):
        cmd = list(map(str, cmd))
        if "train" in cmd:
            run = Path(cmd[cmd.index("--out") + 1])
            for step in (1000, 2000):
                (run / f"checkpoint_{step:07d}.npz").write_bytes(b"x")
        else:
            (Path(cmd[cmd.index("eval") + 1]) / "eval.json").write_text("{}")
        return 0

    monkeypatch.setattr(tool, "_run", fake_run)
    for keep, tag in ((False, "a"), (True, "b")):
        args = tool.argparse.Namespace(test=False, recipe=None, minutes=None, iterations=None, set=[], steps=None,
                                       keep_checkpoints=keep)
        run = tool.train_and_eval("traction", 0, args, tmp_path / "shared", tmp_path / "out" / tag)
        assert (run / "eval.json").is_file()
        assert len(list(run.glob("checkpoint_*.npz"))) == (2 if keep else 0)
