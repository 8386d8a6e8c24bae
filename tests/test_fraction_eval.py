"""tools/fraction_eval.py: a synthetic run scored at times between its frames.  At the held-out
frames' own times its figures are eval's (the scene generated again gives the same frames there)."""
from __future__ import annotations

import json

import numpy as np

from conftest import load_tool, tiny_config


def _tool():
    return load_tool("fraction_eval")


def test_fraction_eval_at_the_test_frames_is_evals(rt, tiny_scene, tmp_path, capsys):
    from endowave_cl.data.scene import load_scene
    from endowave_cl.gaussians import upload
    from endowave_cl.metrics import frame_scores
    from endowave_cl.render import render
    from endowave_cl.run_io import load_run
    from endowave_cl.train.trainer import Trainer
    run = tmp_path / "run"
    tr = Trainer(load_scene(tiny_scene), tiny_config(iterations=30, init_points=1500), run, rt, log=lambda s: None)
    tr.train(progress=False)
    out = tmp_path / "fe.json"
    assert _tool().main([str(run), "--factor", "2", "--json", str(out)]) == 0
    got = json.loads(out.read_text())["by_distance"]
    assert set(got) == {"0.5", "1"}          # halves of every pair; the held-out frames, 1 spacing away
    lr = load_run(run)
    params = upload(rt, lr.gaussians)
    inner = [k for k in lr.scene.test_indices if 0 < k < len(lr.scene.frames) - 1]
    want = [frame_scores(render(rt, params, f.camera, f.time).host()["image"], f.image, f.mask)
            for f in (lr.scene.frames[k] for k in inner)]
    assert got["1"]["times"] == len(inner)
    for key in ("psnr", "psnr_masked", "ssim"):
        np.testing.assert_allclose(got["1"][key], np.mean([w[key] for w in want]), rtol=1e-6)
    assert "0.5" in capsys.readouterr().out


def test_fraction_eval_refuses_a_scene_that_is_not_synthetic(rt, tiny_scene, tmp_path, capsys):
    import shutil
    from endowave_cl.data.scene import load_scene
    from endowave_cl.train.trainer import Trainer
    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    (scene / "scene.json").unlink()
    run = tmp_path / "run"
    Trainer(load_scene(scene), tiny_config(iterations=2, init_points=500), run, rt, log=lambda s: None).train(progress=False)
    assert _tool().main([str(run)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "scene.json" in err[-1] and "not a synthetic scene" in err[-1]
