"""tools/quality_run.py: bad input and interruptions end in one line, and the seeds that finished
are still written to --json."""
from __future__ import annotations

import json

from conftest import load_tool


def load():
    return load_tool("quality_run")


def _row(seed):
    return {"psnr": 30.0 + seed, "psnr_masked": 30.0 + seed, "ssim": 0.9, "lpips": 0.05, "train_psnr": 35.0,
            "baselines": {"mean": {"psnr": 29.0}}, "margin": {"psnr": 1.0 + seed}, "flow": None, "depth": None,
            "gaussians": 100, "steps": 10, "train_seconds": 1.0, "seed": seed}


def test_missing_scene_is_one_line(tmp_path, capsys):
    out = tmp_path / "q.json"
    rc = load().main([str(tmp_path / "nope"), "--out", str(tmp_path / "runs"), "--json", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and len(err) == 1
    assert err[0].startswith("quality_run: error: ") and "nope" in err[0] and "Traceback" not in err[0]
    assert not out.exists()


def test_interrupt_keeps_the_finished_seeds(tmp_path, capsys, monkeypatch):
    mod = load()

    def run_one(scene, downscale, seed, overrides, minutes, out_root):
        if seed == 0:
            return _row(0)
        raise KeyboardInterrupt("stopped by SIGTERM at step 5; saved somewhere")
    monkeypatch.setattr(mod, "run_one", run_one)
    out = tmp_path / "q.json"
    rc = mod.main([str(tmp_path), "--seeds", "0", "1", "--out", str(tmp_path / "runs"), "--json", str(out)])
    cap = capsys.readouterr()
    assert rc == 130
    assert "seed 0: test PSNR 30.00" in cap.out
    err = cap.err.strip().splitlines()
    assert len(err) == 1 and "stopped by SIGTERM at step 5" in err[0] and "1 finished seed(s)" in err[0]
    runs = json.loads(out.read_text())["runs"]
    assert [r["seed"] for r in runs] == [0]
