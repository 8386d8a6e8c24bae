"""Training curves (issue 58): RUN/train_curves.csv always (rewritten atomically each log step), the
PNG at the end, TensorBoard scalars when the package is there, and eval pointing at them."""
from __future__ import annotations

import csv
import json

import pytest

from endowave_cl.cli import main
from endowave_cl.train import curves


def test_csv_columns_and_png(tmp_path):
    hist = [{"step": 0, "total": 1.0, "psnr": 10.0, "rgb": 0.5, "flow": 0.2, "gaussians": 100, "step_ms": 30.0},
            {"step": 50, "total": 0.5, "psnr": 20.0, "rgb": 0.3, "flow": 0.1, "gaussians": 120, "step_ms": 20.0}]
    path = curves.write_csv(tmp_path, hist)
    rows = list(csv.DictReader(path.open()))
    assert list(rows[0]) == ["step", "total", "psnr", "gaussians", "step_ms", "flow", "rgb"]
    assert rows[1]["step"] == "50" and float(rows[1]["psnr"]) == 20.0
    png = curves.write_png(tmp_path, hist, title="t")
    assert png.read_bytes().startswith(b"\x89PNG")
    assert curves.write_png(tmp_path / "x", hist[:1]) is None      # one row: no plot


def test_tensorboard_rows_when_available(tmp_path, monkeypatch):
    seen = []

    class Writer:
        def add_scalar(self, tag, value, step):
            seen.append((tag, value, step))

        def flush(self):
            pass

        def close(self):
            pass
    tb = curves.TensorBoard(tmp_path)
    tb.writer = Writer()            # whatever the package's presence, the rows it would get
    tb.add({"step": 7, "total": 0.5, "psnr": 21.0, "gaussians": 10, "step_ms": 3.0})
    assert ("loss/total", 0.5, 7) in seen and ("train/psnr", 21.0, 7) in seen
    tb.close()
    try:
        import tensorboard  # noqa: F401
    except ImportError:
        assert not curves.TensorBoard(tmp_path).active     # absent: nothing, and no error


@pytest.mark.slow
def test_train_writes_curves_and_eval_names_them(tiny_scene, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["train", str(tiny_scene), "--out", str(run), "--iterations", "8", "--quiet", "--no-flow",
                 "--no-wavelet", "--set", "between_prob=0", "--set", "log_every=2",
                 "--set", "init_points=400"]) == 0
    rows = list(csv.DictReader((run / curves.CSV_NAME).open()))
    assert [int(r["step"]) for r in rows] == [2, 4, 6, 8]
    assert all(float(r["step_ms"]) > 0 and int(r["gaussians"]) > 0 for r in rows)
    assert (run / curves.PNG_NAME).read_bytes().startswith(b"\x89PNG")
    hist = json.loads((run / "train_log.json").read_text())["history"]
    assert len(hist) == len(rows)
    capsys.readouterr()
    assert main(["eval", str(run), "--no-baselines", "--fps-runs", "0"]) == 0
    assert "training curves: " + str(run / curves.PNG_NAME) in capsys.readouterr().out
