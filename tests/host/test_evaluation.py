"""evaluation.py and `endowave-cl eval`: the model beside the baselines, the rendered flow against
gt_flow, the figures, and the cheap training-time call.  Models are hand-made Gaussians (no
training), so these tests stay fast and do not depend on the training method."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

# 12 frames: test frames 1 and 9 both have a next frame, so both have gt_flow
SIZE = dict(width=64, height=48, frames=12, deformation=2.0)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    from endowave_cl.data.synth import make_synthetic_scene
    return make_synthetic_scene(tmp_path_factory.mktemp("ev") / "synth", seed=1, **SIZE)


def _gaussians(static: bool, n: int = 1500, seed: int = 0):
    """Random Gaussians over the synthetic camera's view (depth ~4.4); static = identity 4D
    rotations, so no Gaussian moves and the rendered flow is exactly 0."""
    from endowave_cl.gaussians import Gaussians
    g = Gaussians.random(n, seed=seed, center=(0.0, 0.0, 4.4), spread=1.6, scale=0.12)
    if static:
        g.quat_l[:] = (1, 0, 0, 0)
        g.quat_r[:] = (1, 0, 0, 0)
    return g


def test_training_time_call_is_cheap_and_unchanged(rt, scene_dir, monkeypatch):
    """Trainer.evaluate's call: no baselines, no LPIPS, no FPS; the flow check is there for gt_flow."""
    from endowave_cl import evaluation
    from endowave_cl.data.scene import load_scene
    from endowave_cl.evaluation import evaluate_run
    from endowave_cl.gaussians import upload

    def boom(*a, **k):
        raise AssertionError("baselines computed in the training-time evaluation")
    monkeypatch.setattr(evaluation, "baseline_scores", boom)   # baselines.baseline_scores as evaluation imports it
    scene = load_scene(scene_dir)
    m = evaluate_run(rt, upload(rt, _gaussians(False)), scene, fps_runs=0, with_lpips=False)
    assert m["lpips"] is None and m["fps"] is None and "baselines" not in m and "margin" not in m
    assert m["test_frames"] == 2 and [r["index"] for r in m["per_frame"]] == [1, 9]
    assert m["psnr"] == pytest.approx(np.mean([r["model"]["psnr"] for r in m["per_frame"]]))
    assert m["flow"]["frames"] == 2
    json.dumps(m)                                             # the trainer writes it to train_log.json


def test_rendered_flow_error_against_gt_flow(rt, scene_dir):
    from endowave_cl.data.flow import valid_mask
    from endowave_cl.data.scene import load_scene
    from endowave_cl.evaluation import evaluate_run
    from endowave_cl.gaussians import upload
    from endowave_cl.render import render
    scene = load_scene(scene_dir)
    # a model that does not move: its error is the true motion's magnitude, the error of zero flow
    m0 = evaluate_run(rt, upload(rt, _gaussians(True)), scene, fps_runs=0, with_lpips=False)["flow"]
    assert m0["model_magnitude"] == 0.0
    assert m0["model_epe"] == pytest.approx(m0["gt_magnitude"], rel=1e-6) and m0["gt_magnitude"] > 0.5
    assert m0["dis_epe"] < m0["gt_magnitude"]                 # DIS sees the motion
    # a moving model, against an independent computation from the files
    params = upload(rt, _gaussians(False))
    m = evaluate_run(rt, params, scene, fps_runs=0, with_lpips=False)
    errs, mags = [], []
    for k in (1, 9):
        f0, f1 = scene.frames[k], scene.frames[k + 1]
        flow = render(rt, params, f0.camera, f0.time, f1.time).host()["flow"]
        gt = np.load(scene_dir / "gt_flow" / f"{k:06d}.npy")
        valid = valid_mask(gt, None, f0.mask, f1.mask) > 0.5
        assert valid.sum() > 0.5 * valid.size and not np.any(valid & (f0.mask == 0))   # tissue only
        errs.append(np.linalg.norm(flow - gt, axis=-1)[valid].mean())
        mags.append(np.linalg.norm(flow, axis=-1)[valid].mean())
        row = next(r for r in m["per_frame"] if r["index"] == k)
        assert row["flow"]["pixels"] == int(valid.sum())
    assert np.mean(mags) > 0.05                               # this model does move
    assert m["flow"]["model_epe"] == pytest.approx(np.mean(errs), rel=1e-5)
    assert m["flow"]["model_magnitude"] == pytest.approx(np.mean(mags), rel=1e-5)
    assert m["flow"]["dis_epe"] == m0["dis_epe"]


def test_depth_error_against_the_depth_maps_in_the_files_units(rt, scene_dir):
    import copy
    import math
    from endowave_cl.data.scene import load_scene
    from endowave_cl.evaluation import evaluate_run
    from endowave_cl.gaussians import upload
    from endowave_cl.render import render
    g = _gaussians(True)
    s1 = load_scene(scene_dir, world_scale=1.0)
    m1 = evaluate_run(rt, upload(rt, g), s1, fps_runs=0, with_lpips=False)["depth"]
    # by hand: |depth / alpha - depth map| over valid tissue pixels of the test frames
    errs, true = [], []
    for k in s1.test_indices:
        f = s1.frames[k]
        h = render(rt, upload(rt, g), f.camera, f.time).host()
        ok = (f.depth > 0) & (f.mask > 0.5)
        errs.append(np.abs(h["depth"] / np.maximum(h["alpha"], 1e-6) - f.depth)[ok])
        true.append(f.depth[ok])
    mae = np.concatenate(errs).mean()
    assert m1["frames"] == 2 and m1["pixels"] == sum(e.size for e in errs)
    assert m1["mae"] == pytest.approx(mae, rel=1e-6)
    assert m1["relative"] == pytest.approx(mae / np.concatenate(true).mean(), rel=1e-6)
    assert 0 < m1["relative"] < 1
    # the same model and scene measured in units 2.5 times smaller: the same error in the files' units
    g2 = copy.deepcopy(g)
    g2.means[:, :3] *= 2.5
    g2.scales[:, :3] += math.log(2.5)
    m2 = evaluate_run(rt, upload(rt, g2), load_scene(scene_dir, world_scale=2.5), fps_runs=0, with_lpips=False)
    assert m2["depth"]["mae"] == pytest.approx(m1["mae"], rel=1e-3)
    assert m2["depth"]["relative"] == pytest.approx(m1["relative"], rel=1e-3)
    # a scene without depth maps: no depth figures
    assert evaluate_run(rt, upload(rt, g), load_scene(scene_dir, use_depth=False), fps_runs=0,
                        with_lpips=False)["depth"] is None


def test_flow_image_channel_does_not_change_the_scored_image(rt, scene_dir):
    """The evaluation renders test frames with a flow time; the image must be the one without."""
    from endowave_cl.data.scene import load_scene
    from endowave_cl.gaussians import upload
    from endowave_cl.render import render
    scene = load_scene(scene_dir)
    params = upload(rt, _gaussians(False))
    f = scene.frames[1]
    a = render(rt, params, f.camera, f.time).host()["image"]
    b = render(rt, params, f.camera, f.time, scene.frames[2].time).host()["image"]
    np.testing.assert_array_equal(a, b)


def test_gt_flow_of_a_downscaled_scene_and_bad_files(scene_dir, tmp_path):
    import shutil

    from endowave_cl.data.scene import load_scene
    from endowave_cl.errors import DataError
    from endowave_cl.evaluation import flow_references
    half = flow_references(load_scene(scene_dir, downscale=2))
    gt = np.load(scene_dir / "gt_flow" / "000001.npy")
    assert half[1][0].shape == (24, 32, 2)
    np.testing.assert_allclose(half[1][0], cv2.resize(gt, (32, 24), interpolation=cv2.INTER_LINEAR) / 2,
                               atol=1e-5)
    bad = tmp_path / "bad"
    shutil.copytree(scene_dir, bad)
    np.save(bad / "gt_flow" / "000001.npy", np.zeros((48, 64, 3), np.float32))
    with pytest.raises(DataError, match=r"000001\.npy.*\[H, W, 2\]"):
        flow_references(load_scene(bad))
    (bad / "gt_flow" / "000001.npy").write_bytes(b"not numpy")
    with pytest.raises(DataError, match=r"000001\.npy: unreadable"):
        flow_references(load_scene(bad))
    shutil.rmtree(bad / "gt_flow")
    assert flow_references(load_scene(bad)) == {}           # real scenes: no flow check


def _run_folder(path, scene_dir, g):
    """A run folder as `endowave-cl train` leaves it: config.json and a checkpoint."""
    from endowave_cl.atomic import write_bytes_atomic
    from endowave_cl.checkpoint import checkpoint_path, save_checkpoint
    from endowave_cl.train.config import TrainConfig
    cfg = TrainConfig().to_dict()
    path.mkdir()
    write_bytes_atomic(path / "config.json", json.dumps({"scene": str(scene_dir), **cfg}).encode())
    save_checkpoint(checkpoint_path(path, 7), g, None, 7, cfg, {})
    return path


def test_eval_command_baselines_margin_flow_and_figures(rt, scene_dir, tmp_path, capsys):
    from endowave_cl.baselines import baseline_images
    from endowave_cl.cli import main
    from endowave_cl.data.scene import load_scene
    from endowave_cl.lpips import lpips_available
    from endowave_cl.metrics import frame_scores
    run = _run_folder(tmp_path / "run", scene_dir, _gaussians(False))
    assert main(["eval", str(run), "--fps-runs", "1"]) == 0
    out = capsys.readouterr().out
    m = json.loads((run / "eval.json").read_text())
    assert {"psnr", "psnr_masked", "ssim", "lpips", "fps", "baselines", "margin", "flow", "per_frame"} <= set(m)
    assert m["step"] == 7 and (m["lpips"] is None) != lpips_available()
    # the baselines in eval.json are the test frames' baselines, scored like the model
    scene = load_scene(scene_dir)
    for name in ("mean", "dis", "dis_cubic", "teacher"):
        per = [frame_scores(baseline_images(scene, k)[name], scene.frames[k].image, scene.frames[k].mask)
               for k in scene.test_indices]
        assert m["baselines"][name]["psnr"] == pytest.approx(np.mean([p["psnr"] for p in per]), abs=1e-6)
        assert m["baselines"][name]["psnr_masked"] == pytest.approx(np.mean([p["psnr_masked"] for p in per]), abs=1e-6)
        assert m["baselines"][name]["ssim"] == pytest.approx(np.mean([p["ssim"] for p in per]), abs=1e-6)
    assert m["per_frame"][0]["neighbours"] == [0, 2] and m["per_frame"][0]["fraction"] == 0.5
    best = max(("mean", "dis", "dis_cubic", "teacher"), key=lambda n: m["baselines"][n]["psnr"])
    assert m["margin"]["over"] == best
    assert m["margin"]["psnr"] == pytest.approx(m["psnr"] - m["baselines"][best]["psnr"])
    assert m["margin"]["psnr_masked"] == pytest.approx(m["psnr_masked"] - m["baselines"][best]["psnr_masked"])
    assert m["margin_teacher"]["psnr"] == pytest.approx(m["psnr"] - m["baselines"]["teacher"]["psnr"])
    assert m["per_frame"][0]["motion"] > 0 and m["train_fit"]["frames"] == len(scene.train_indices)
    # the printed table
    for text in ("neighbour mean", "DIS flow interpolation", "in-between teacher", "margin over the",
                 "end-point error model", "depth vs the depth maps", "training frames: PSNR"):
        assert text in out, out
    assert f"{m['margin']['psnr']:+.2f} dB" in out
    # the figures: a plot, and the worst frame as ground truth | render | error at full resolution
    plot = cv2.imread(str(run / "eval_per_frame.png"))
    assert plot is not None and plot.shape[0] > 200
    worst = cv2.imread(str(run / "eval_worst.png"))
    from endowave_cl.evaluation import LABEL_HEIGHT
    assert worst.shape == (LABEL_HEIGHT + 48, 3 * 64 + 8, 3)
    assert worst[:LABEL_HEIGHT, :64].min() < 100                                  # a label above each panel
    assert worst[:LABEL_HEIGHT, 68:132].min() < 100 and worst[:LABEL_HEIGHT, 136:].min() < 100
    k = min(m["per_frame"], key=lambda r: r["model"]["psnr"])["index"]
    assert m["worst_frame"] == k
    gt8 = (scene.frames[k].image[..., ::-1] * 255 + 0.5).astype(np.uint8)        # left panel, BGR
    np.testing.assert_array_equal(worst[LABEL_HEIGHT:, :64], gt8)
    assert not any(p.name.endswith(".tmp") for p in run.iterdir())                 # atomic writes


def test_eval_command_without_baselines_and_bad_input(rt, scene_dir, tmp_path, capsys):
    from endowave_cl.cli import main
    run = _run_folder(tmp_path / "run", scene_dir, _gaussians(True))
    assert main(["eval", str(run), "--fps-runs", "0", "--no-baselines"]) == 0
    m = json.loads((run / "eval.json").read_text())
    assert "baselines" not in m and m["fps"] is None and (run / "eval_per_frame.png").is_file()
    assert "margin over" not in capsys.readouterr().out
    assert main(["eval", str(run), "--fps-runs", "-1"]) == 1
    err = capsys.readouterr().err
    assert "--fps-runs must be >= 0" in err and len(err.strip().splitlines()) == 1


def test_validation_split_never_trains_or_scores_a_test_frame(scene_dir):
    from endowave_cl.data.scene import apply_split, load_scene, validation_indices
    from endowave_cl.errors import DataError
    for n in (2, 6, 7, 12, 63, 129):
        val = validation_indices(n)
        test = {i for i in range(n) if (i - 1) % 8 == 0}
        assert all((i - 5) % 8 == 0 and 0 < i < n - 1 for i in val) and not set(val) & test
        # like a test frame, each has its two neighbours among the training frames
        train = set(range(n)) - test - set(val)
        assert all({i - 1, i + 1} <= train for i in val)
    assert validation_indices(63) == [5, 13, 21, 29, 37, 45, 53, 61]
    scene = apply_split(load_scene(scene_dir), "validation")
    assert scene.test_indices == [5] and scene.split == "validation"
    assert set(scene.train_indices) == {0, 2, 3, 4, 6, 7, 8, 10, 11}
    assert "1 validation" in scene.summary()
    with pytest.raises(DataError, match="split must be one of"):
        apply_split(load_scene(scene_dir), "train")


def test_teacher_is_the_static_in_between_target(scene_dir):
    """The teacher baseline is what an in-between step with the default keys trains on at the test
    frame's time (the same between_target call the trainer makes, the model's part off), and it
    interpolates the synthetic motion better than the neighbour mean."""
    from endowave_cl.baselines import baseline_images, teacher_for
    from endowave_cl.data.flow import flow_for_scene
    from endowave_cl.data.scene import load_scene
    from endowave_cl.metrics import psnr
    from endowave_cl.train.between import between_target, consistent_flows, extra_pairs, pair_bend, usable_pairs
    from endowave_cl.train.config import TrainConfig, between_flow_methods
    scene, c = load_scene(scene_dir), TrainConfig()
    own = dict(flow_for_scene(scene, method=c.flow_method, progress=False, max_pixels=c.flow_max_pixels))
    others = [dict(flow_for_scene(scene, method=m, progress=False, max_pixels=c.flow_max_pixels))
              for m in between_flow_methods(c)]
    pairs = usable_pairs(scene, own)
    index = [p.src for p in pairs].index(0)
    pair = pairs[index]
    assert (pair.src, pair.dst) == (0, 2)

    def sources(p):
        return [p, *extra_pairs(others, p)]
    bend = pair_bend(scene, pairs, index, sources, lambda i: consistent_flows(sources(pairs[i])))
    want = between_target(scene, pair, 0.5, extra_pairs(others, pair), fuse=c.between_fuse,
                          flow_splat=c.between_flow_splat, bend=bend)[0]
    teacher = teacher_for(scene)
    got = teacher.image(0, 2, 0.5)
    np.testing.assert_array_equal(got, np.clip(want, 0, 1))
    assert teacher.image(0, 3, 0.5) is None                      # not a training pair
    images = baseline_images(scene, 1, teacher)
    np.testing.assert_array_equal(images["teacher"], got)
    gt = scene.frames[1].image
    assert psnr(images["teacher"], gt) > psnr(images["mean"], gt) + 3
