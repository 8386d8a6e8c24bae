"""tools/interp_paths.py: straight and curved paths in a flow interpolation of the held-out frames.
Its straight column is the bicubic DIS baseline (baselines.py, computed independently); the curved
one differs where the synthetic tissue changes speed; a scene where no test frame has two training
frames on each side says so."""
from __future__ import annotations

import pytest

from conftest import load_tool


def test_interp_paths_straight_is_the_bicubic_dis_baseline(tmp_path_factory, capsys):
    from endowave_cl.baselines import baseline_images
    from endowave_cl.data.scene import load_scene
    from endowave_cl.metrics import psnr
    from endowave_cl.data.synth import make_synthetic_scene
    path = tmp_path_factory.mktemp("scene") / "paths"
    make_synthetic_scene(path, width=64, height=48, frames=14, seed=5)
    assert load_tool("interp_paths").main([str(path)]) == 0
    out = capsys.readouterr().out
    rows = {int(line.split()[0]): [float(x) for x in line.split()[1:]] for line in out.splitlines()
            if line.split() and line.split()[0].isdigit()}
    assert list(rows) == [9]                 # test frames 1 and 9; only 9 has training frames 7, 8 | 10, 11
    sc = load_scene(path)
    base = baseline_images(sc, 9)
    mean, straight, curved, disp, bend = rows[9]
    assert mean == pytest.approx(psnr(base["mean"], sc.frames[9].image), abs=0.006)
    assert straight == pytest.approx(psnr(base["dis_cubic"], sc.frames[9].image), abs=0.006)
    assert bend > 0.0 and disp > 0.0 and curved != straight
    assert "mean" in out and "(1 test frames)" in out


def test_interp_paths_without_frames_beyond_the_pair(tiny_scene, capsys):
    assert load_tool("interp_paths").main([str(tiny_scene)]) == 0
    assert "no test frame has two training frames on each side" in capsys.readouterr().out
