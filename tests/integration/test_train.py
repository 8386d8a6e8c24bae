"""End-to-end training on a tiny synthetic scene: PSNR rises, resume, bad input, NaN guard."""
from __future__ import annotations

import shutil
import subprocess
import sys

import numpy as np
import pytest

from conftest import tiny_config

pytestmark = pytest.mark.slow


def _cfg(**kw):
    return tiny_config(**{**dict(iterations=150, init_points=3000, densify_from=50, densify_every=50,
                                 densify_until=100, log_every=25), **kw})


def test_short_training_raises_test_psnr(rt, tiny_scene, tmp_path):
    from endowave_cl.data.scene import load_scene
    from endowave_cl.train.trainer import Trainer
    scene = load_scene(tiny_scene)
    tr = Trainer(scene, _cfg(), tmp_path / "run", rt, log=lambda s: None)
    before = tr.evaluate()["psnr"]
    after = tr.train(progress=False)["psnr"]
    print(f"test PSNR {before:.2f} -> {after:.2f} dB")
    assert after > before + 3.0
    assert (tmp_path / "run" / "train_log.json").is_file()


def test_resume_continues_from_checkpoint(rt, tiny_scene, tmp_path):
    from endowave_cl.data.scene import load_scene
    from endowave_cl.gaussians import download
    from endowave_cl.train.trainer import Trainer
    scene = load_scene(tiny_scene)
    run = tmp_path / "run"
    tr = Trainer(scene, _cfg(iterations=40, use_flow=False), run, rt, log=lambda s: None)
    tr.train(progress=False)
    g1 = download(tr.params)
    msgs = []
    tr2 = Trainer(scene, _cfg(iterations=60, use_flow=False), run, rt, log=msgs.append)
    assert tr2.step == 40 and any("resuming" in m for m in msgs)
    np.testing.assert_array_equal(download(tr2.params).means, g1.means)
    m1 = tr.adam.state_dict()
    m2 = tr2.adam.state_dict()
    for k in m1:
        if isinstance(m1[k], np.ndarray):
            np.testing.assert_array_equal(m1[k], m2[k])
    tr2.train(progress=False)
    assert tr2.step == 60


def test_a_run_keeps_its_scene_units(rt, tiny_scene, tmp_path):
    """Checkpoints record the scene units; resuming and load_run use them, and a checkpoint from
    before scene units (no world_scale) is read in the files' own units."""
    from endowave_cl.checkpoint import latest_checkpoint, load_checkpoint, save_checkpoint
    from endowave_cl.data.scene import load_scene
    from endowave_cl.run_io import load_run
    from endowave_cl.train.trainer import Trainer
    scene = load_scene(tiny_scene)
    assert scene.world_scale != 1.0
    run = tmp_path / "run"
    Trainer(scene, _cfg(iterations=20, use_flow=False), run, rt, log=lambda s: None).train(progress=False)
    ck_path = latest_checkpoint(run)
    ck = load_checkpoint(ck_path)
    assert ck["extra"]["world_scale"] == scene.world_scale
    assert load_run(run).scene.world_scale == scene.world_scale
    # the same checkpoint without the key, as an older version wrote it
    extra = {k: v for k, v in ck["extra"].items() if k != "world_scale"}
    save_checkpoint(ck_path, ck["gaussians"], ck["adam_state"], ck["step"], ck["config"], extra)
    assert load_run(run).scene.world_scale == 1.0
    fresh = load_scene(tiny_scene)
    tr = Trainer(fresh, _cfg(iterations=25, use_flow=False), run, rt, log=lambda s: None)
    assert tr.step == 20 and fresh.world_scale == 1.0
    np.testing.assert_allclose(fresh.frames[0].depth, load_scene(tiny_scene, world_scale=1.0).frames[0].depth,
                               rtol=1e-5)


def _cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "endowave_cl", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=600)


def test_missing_scene_and_corrupt_frame_errors_keep_earlier_run(rt, tiny_scene, tmp_path):
    run = tmp_path / "run"
    r = _cli("train", str(tiny_scene), "--out", str(run), "--iterations", "5", "--quiet", "--no-flow",
             "--set", "checkpoint_every=5", "--set", "init_points=500")
    assert r.returncode == 0, r.stderr
    assert "colour SH degree 1 (one camera centre)" in r.stdout, r.stdout   # sh_degree -1, a fixed camera
    assert "Gaussians (density control up to " in r.stdout, r.stdout
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    assert any(n.startswith("checkpoint_") for n in before)

    r = _cli("train", str(tmp_path / "no_such_scene"), "--out", str(run), "--quiet")
    assert r.returncode == 1 and "no_such_scene" in r.stderr and "Traceback" not in r.stderr

    bad = tmp_path / "bad"
    shutil.copytree(tiny_scene, bad)
    frame = sorted((bad / "images").glob("*.png"))[2]
    frame.write_bytes(frame.read_bytes()[:100])   # truncated PNG
    r = _cli("train", str(bad), "--out", str(run), "--quiet")
    assert r.returncode == 1 and frame.name in r.stderr, r.stderr
    after = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    assert after == before


def test_nan_step_is_caught_and_not_applied(rt, tiny_scene, tmp_path):
    from endowave_cl.data.scene import load_scene
    from endowave_cl.gaussians import download
    from endowave_cl.train.trainer import Trainer, TrainingDiverged
    scene = load_scene(tiny_scene)
    tr = Trainer(scene, _cfg(iterations=10, use_flow=False), tmp_path / "run", rt, log=lambda s: None)
    k = scene.train_indices[0]
    img = tr.targets[k].dev.image                 # a NaN in the data makes the loss NaN
    host = img.get()
    host[5, 7, 1] = float("nan")
    img.set(host)
    before = download(tr.params)
    with pytest.raises(TrainingDiverged, match="non-finite"):
        tr.train_step(k)
    after = download(tr.params)
    np.testing.assert_array_equal(after.means, before.means)   # the step was not applied
    assert tr.step == 0


def test_eval_render_export_commands(rt, tiny_scene, tmp_path):
    run = tmp_path / "run"
    r = _cli("train", str(tiny_scene), "--out", str(run), "--iterations", "20", "--quiet", "--no-flow",
             "--set", "init_points=800")
    assert r.returncode == 0, r.stderr
    assert "final test PSNR" in r.stdout
    r = _cli("eval", str(run), "--fps-runs", "2")
    assert r.returncode == 0, r.stderr
    import json
    m = json.loads((run / "eval.json").read_text())
    assert {"psnr", "psnr_masked", "ssim", "lpips", "fps"} <= set(m) and m["fps"] > 0
    from endowave_cl.lpips import lpips_available
    assert (m["lpips"] is None) != lpips_available()
    r = _cli("render", str(run), "--no-video")
    assert r.returncode == 0, r.stderr
    assert len(list((run / "render" / "frames").glob("*.png"))) == 2   # frames 1 and 9 of 10
    assert len(list((run / "render" / "depth").glob("*.png"))) == 2
    assert len(list((run / "render" / "depth_colour").glob("*.png"))) == 2   # turbo beside the raw 16-bit
    r = _cli("export", str(run), "--time", "0.5", "--out", str(tmp_path / "m.ply"))
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "m.ply").read_bytes().startswith(b"ply\n")
    r = _cli("eval", str(tmp_path / "nowhere"))
    assert r.returncode == 1 and "not a training run" in r.stderr


def test_steps_whose_pairs_overflow_are_done_again_to_the_same_bits(rt, tiny_scene, tmp_path, monkeypatch):
    """Every binning given pair buffers too small (ops/binning.py): the training step sees the
    overflow after its read-back and does the step again from a checked render, and the in-between
    step's motion render is rendered again; the parameters end bit-identical to a run with room."""
    from endowave_cl.data.scene import load_scene
    from endowave_cl.gaussians import PARAM_NAMES, download
    from endowave_cl.ops import binning as B
    from endowave_cl.train.trainer import Trainer
    scene = load_scene(tiny_scene)
    cfg = _cfg(iterations=24, densify_from=8, densify_every=8, densify_until=16, between_motion_refresh=4)

    def trained(name):
        tr = Trainer(scene, cfg, tmp_path / name, rt, log=lambda s: None)
        tr.train(progress=False)
        return download(tr.params)
    want = trained("room")
    seen = []
    plain = B.PairCount.overflowed.fget

    def tiny(rt_, tiles_x, tiles_y):
        p = B.PairCapacity()
        p.capacity = 8
        return p

    def overflowed(pairs):
        seen.append(plain(pairs))
        return seen[-1]
    monkeypatch.setattr(B, "pair_capacity", tiny)
    monkeypatch.setattr(B.PairCount, "overflowed", property(overflowed))
    got = trained("tiny")
    assert sum(seen) >= cfg.iterations                  # every step's first render overflowed
    for name in PARAM_NAMES:
        assert np.array_equal(getattr(got, name), getattr(want, name)), name
