"""The baselines eval puts beside the model (baselines.py): neighbour mean and DIS flow
interpolation, checked against independent computations on known frame pairs."""
from __future__ import annotations

import math
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from endowave_cl import baselines as B
from endowave_cl.errors import EndowaveError
from endowave_cl.metrics import frame_scores


def _texture(h=96, w=128, seed=0):
    """Smooth random RGB texture in [0.1, 0.9] (blobs a few pixels wide: DIS can track it)."""
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.standard_normal((h, w, 3)).astype(np.float32), (0, 0), 2.5)
    t = (t - t.min()) / (t.max() - t.min())
    return (0.1 + 0.8 * t).astype(np.float32)


def _shift(img, dx, dy=0.0):
    """img translated by (dx, dy) pixels (content moves right/down for positive values)."""
    m = np.float32([[1, 0, dx], [0, 1, dy]])
    return cv2.warpAffine(img, m, (img.shape[1], img.shape[0]), flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT)


def _psnr(a, b):
    return 10 * math.log10(1 / float(np.mean((np.float64(a) - np.float64(b)) ** 2)))


def _scene(images, train, test, masks=None, times=None):
    n = len(images)
    times = times or [i / (n - 1) for i in range(n)]
    h, w = images[0].shape[:2]
    camera = SimpleNamespace(width=w, height=h, fx=1.0, fy=1.0, cx=0.0, cy=0.0, viewmat=np.eye(4))   # one viewpoint
    frames = [SimpleNamespace(time=times[i], image=images[i], mask=None if masks is None else masks[i],
                              name=f"{i:06d}", camera=camera) for i in range(n)]
    return SimpleNamespace(path=f"/nonexistent/stub-{id(frames)}", frames=frames, train_indices=train,
                           test_indices=test, width=w, height=h)


def test_neighbours_middle_ends_and_time_fraction():
    imgs = [np.zeros((4, 4, 3), np.float32)] * 10
    sc = _scene(imgs, train=[0, 2, 3, 4, 5, 6, 7, 8], test=[1, 9])
    assert B.neighbours(sc, 1) == (0, 2, 0.5)
    assert B.neighbours(sc, 9) == (8, 8, 0.0)                 # sequence end: the one available
    sc2 = _scene(imgs, train=[2, 3, 4, 5, 6, 7, 8, 9], test=[0, 1])
    assert B.neighbours(sc2, 0) == (2, 2, 0.0) and B.neighbours(sc2, 1) == (2, 2, 0.0)
    sc3 = _scene(imgs, train=[0, 4, 9], test=[1, 2, 3])       # not midway: fraction by time
    i0, i1, a = B.neighbours(sc3, 1)
    assert (i0, i1) == (0, 4) and a == pytest.approx(0.25)
    # unequal time steps: the fraction follows time, not frame numbers
    times = [0.0, 0.1, 0.4] + [0.5 + 0.05 * i for i in range(7)]
    sc4 = _scene(imgs, train=[0, 2], test=[1], times=times)
    assert B.neighbours(sc4, 1)[2] == pytest.approx(0.25)
    with pytest.raises(EndowaveError, match="no training frame"):
        B.neighbours(_scene(imgs[:2], train=[], test=[0, 1]), 0)


def test_mean_baseline_is_the_exact_average():
    a, b = _texture(seed=1), _texture(seed=2)
    sc = _scene([a, 0.5 * (a + b), b], train=[0, 2], test=[1])
    got = B.baseline_images(sc, 1)["mean"]
    np.testing.assert_allclose(got, (a.astype(np.float64) + b) / 2, atol=1e-6)
    np.testing.assert_allclose(B.mean_interpolation(a, b, 0.25), 0.75 * a + 0.25 * b, atol=1e-6)


@pytest.mark.parametrize("a", [0.5, 0.25])
def test_dis_interpolation_recovers_a_translated_pattern(a):
    """Frames 0 and 1 are a texture moved 4 px apart along a diagonal; the truth at time fraction a
    lies a of the way.  DIS interpolation must reproduce it (inside a border margin) far better
    than the blend of the two frames, which ghosts."""
    tex = _texture(seed=3)
    d = np.array([4.0, -2.0])
    f0, f1 = _shift(tex, *(-a * d)), _shift(tex, *((1 - a) * d))   # truth at a is tex itself
    got = B.dis_interpolation(f0, f1, a)
    blend = B.mean_interpolation(f0, f1, a)
    inner = (slice(10, -10), slice(10, -10))
    p_dis, p_mean = _psnr(got[inner], tex[inner]), _psnr(blend[inner], tex[inner])
    print(f"a={a}: DIS interpolation {p_dis:.2f} dB, blend {p_mean:.2f} dB")
    assert p_dis > 35.0 and p_dis > p_mean + 10.0
    cubic = B.dis_interpolation(f0, f1, a, sampler="cubic")     # the same flows, bicubic warps
    assert _psnr(cubic[inner], tex[inner]) > 35.0
    assert B.dis_interpolations(f0, f1, a, samplers=("linear", "cubic"))["linear"].tobytes() == got.tobytes()


def test_the_bicubic_dis_baseline_is_the_straight_path_interpolation():
    """dis_cubic warps each frame along its own flow, the in-between target's straight path
    (train/between.py path_displacement without the frames beyond the pair): the two agree, as
    research/interp_paths.py's straight column assumes (moved here from tests/test_interp_paths.py)."""
    from endowave_cl.data.flow import estimate_flow
    from endowave_cl.train.between import path_displacement
    tex = _texture(seed=6)
    d, a, span = np.array([3.0, 1.5]), 0.25, 0.2
    f0, f1 = _shift(tex, *(-a * d)), _shift(tex, *((1 - a) * d))
    f01, f10 = estimate_flow(f0, f1), estimate_flow(f1, f0)
    g0, g1 = path_displacement(f01, a, span), path_displacement(f10, 1.0 - a, -span)
    straight = B.mean_interpolation(B.sample_displaced(f0, -g0, "cubic"), B.sample_displaced(f1, -g1, "cubic"), a)
    np.testing.assert_allclose(straight, B.dis_interpolations(f0, f1, a, samplers=("cubic",))["cubic"], atol=1e-6)


def test_warp_backward_moves_content_along_the_flow():
    tex = _texture(seed=4)
    flow = np.zeros(tex.shape[:2] + (2,), np.float32)
    flow[..., 0] = 6.0                                        # everything moves 6 px right
    moved = B.warp_backward(tex, flow, 0.5)                   # half-way: 3 px right
    np.testing.assert_allclose(moved[:, 3:], tex[:, :-3], atol=1e-5)


def test_baseline_scores_match_an_independent_computation_and_are_cached(monkeypatch):
    a, b, c = _texture(seed=5), _texture(seed=6), _texture(seed=7)
    gt = _shift(a, 1.0, 0.5)
    mask = np.ones(a.shape[:2], np.float32)
    mask[:20, :30] = 0                                        # a "tool" in the corner of the test frame
    sc = _scene([a, gt, b, c], train=[0, 2, 3], test=[1], masks=[None, mask, None, None])
    rows = B.baseline_scores(sc)
    assert [r["index"] for r in rows] == [1] and rows[0]["neighbours"] == [0, 2] and rows[0]["fraction"] == 0.5
    # the neighbour mean's figures, by hand: both PSNR forms
    mean = (a.astype(np.float64) + b) / 2
    sq = (mean - gt) ** 2 * mask[..., None]
    assert rows[0]["mean"]["psnr"] == pytest.approx(10 * math.log10(1 / sq.mean()), abs=1e-4)
    assert rows[0]["mean"]["psnr_masked"] == pytest.approx(10 * math.log10(3 * mask.sum() / sq.sum()), abs=1e-4)
    # and exactly what the model's scoring function gives for the same images
    assert rows[0]["dis"] == frame_scores(B.dis_interpolation(a, b, 0.5), gt, mask)
    assert rows[0]["dis_cubic"] == frame_scores(B.dis_interpolation(a, b, 0.5, sampler="cubic"), gt, mask)
    assert rows[0]["mean"]["lpips"] is None
    summary = B.summarise(rows, "mean")
    assert summary["psnr"] == rows[0]["mean"]["psnr"] and summary["lpips"] is None
    # a second call for the same scene is served from memory
    calls = []
    monkeypatch.setattr(B, "baseline_images", lambda *args: calls.append(args))
    assert B.baseline_scores(sc) is rows and not calls


def _tool(*args):
    import subprocess
    import sys
    from pathlib import Path
    tool = Path(__file__).resolve().parents[2] / "tools" / "eval_baselines.py"
    return subprocess.run([sys.executable, str(tool), *map(str, args)], capture_output=True, text=True, timeout=300)


def test_eval_baselines_tool(tmp_path):
    import json
    from endowave_cl.data.synth import make_synthetic_scene
    scene = make_synthetic_scene(tmp_path / "s", width=48, height=40, frames=12, seed=2, deformation=2.0)
    r = _tool(scene, "--no-lpips", "--per-frame", "--json", tmp_path / "b.json")
    assert r.returncode == 0, r.stderr
    out = json.loads((tmp_path / "b.json").read_text())
    assert set(out["baselines"]) == {"mean", "dis", "dis_cubic", "teacher"} and out["flow"]["frames"] == 2
    for line in ("host: ", "neighbour mean", "DIS flow interpolation", "in-between teacher", "gt_flow: DIS"):
        assert line in r.stdout, r.stdout
    assert f"{out['baselines']['dis']['psnr']:7.2f}" in r.stdout
    r = _tool(tmp_path / "nowhere")
    assert r.returncode == 1 and "nowhere" in r.stderr and "Traceback" not in r.stderr


def test_real_frames_flow_interpolation_beats_the_mean(pulling_scene):
    """On the shared real frames (skipped when absent), at 160x128: the neighbour mean is the plain
    average of frames i - 1 and i + 1, and DIS interpolation is well above it."""
    from endowave_cl.data.scene import load_scene
    sc = load_scene(pulling_scene, downscale=4)
    rows = B.baseline_scores(sc)
    for r in rows:
        k = r["index"]
        assert r["neighbours"] == [k - 1, k + 1] and r["fraction"] == pytest.approx(0.5)
        avg = (sc.frames[k - 1].image.astype(np.float64) + sc.frames[k + 1].image) / 2
        assert r["mean"]["psnr"] == pytest.approx(_psnr(avg, sc.frames[k].image), abs=1e-4)
    mean, dis = B.summarise(rows, "mean")["psnr"], B.summarise(rows, "dis")["psnr"]
    print(f"160x128: neighbour mean {mean:.2f} dB, DIS interpolation {dis:.2f} dB")
    assert dis > mean + 2.0
