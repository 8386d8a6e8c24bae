"""Pseudo ground-truth flow: accuracy against the synthetic truth, consistency mask, cache, files, CLI."""
from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest

from endowave_cl.cli import main as cli_main
from endowave_cl.data import flow as flow_mod
from endowave_cl.data import (flow_for_scene, load_scene, make_synthetic_scene, read_flo, read_flow_file,
                              training_pairs, write_flo)
from endowave_cl.data.flow import estimate_flow, fb_consistent, valid_mask
from endowave_cl.errors import DataError


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """The built-in demo scene: 160x128, 24 frames."""
    return make_synthetic_scene(tmp_path_factory.mktemp("demo") / "scene")


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    return make_synthetic_scene(tmp_path_factory.mktemp("small") / "scene", width=64, height=48, frames=6, seed=2)


def _gt(scene_dir, k):
    return np.load(scene_dir / "gt_flow" / f"{k:06d}.npy")      # [H, W, 2] frame k -> k + 1


def _grid(h, w):
    return np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))


def test_training_pairs_follow_the_training_list(demo):
    scene = load_scene(demo)
    pairs = training_pairs(scene)
    assert pairs[:3] == [(0, 2), (2, 3), (3, 4)] and (8, 10) in pairs and len(pairs) == 20


def test_dis_end_point_error_against_synthetic_truth(demo, tmp_path):
    scene = load_scene(demo)
    result = flow_for_scene(scene, progress=False, cache_dir=tmp_path)
    epe, still, frac = [], [], []
    for k, pair in result.items():
        assert pair.flow.shape == (128, 160, 2) and pair.valid.shape == (128, 160)
        assert pair.flow.dtype == np.float32 and pair.valid.dtype == np.float32
        if pair.dst != k + 1:          # ground truth is written for consecutive frames only
            continue
        gt = _gt(demo, k)
        v = pair.valid > 0
        epe.append(np.linalg.norm(pair.flow - gt, axis=-1)[v].mean())
        still.append(np.linalg.norm(gt, axis=-1)[v].mean())
        frac.append(v.sum() / (scene.frames[k].mask > 0).sum())
    epe, still = float(np.mean(epe)), float(np.mean(still))
    print(f"DIS EPE on valid pixels {epe:.3f} px over {len(frac)} pairs (zero flow would score "
          f"{still:.3f} px); valid {100 * np.mean(frac):.1f}% of tissue pixels")
    # Bound: DIS on a noise-free, textured sequence with ~1 px motion is sub-pixel; we measured
    # 0.14 px.  0.35 px leaves 2.5x headroom for OpenCV versions, yet any real fault (sign, x/y
    # swap, direction, misaligned pairs) costs at least the zero-flow error of about 0.7 px.
    assert epe < 0.35 and epe < 0.5 * still
    assert np.mean(frac) > 0.85       # the mask keeps most tissue


@pytest.mark.parametrize("method", ["dis_fine", "farneback", "deepflow", "tvl1"])
def test_other_methods_are_accurate_too(small, method):
    scene = load_scene(small)
    f0, f1 = scene.frames[2], scene.frames[3]
    flow = estimate_flow(f0.image, f1.image, method)
    gt = _gt(small, 2)
    inner = (f0.mask > 0)
    inner[:4], inner[-4:], inner[:, :4], inner[:, -4:] = False, False, False, False
    epe = np.linalg.norm(flow - gt, axis=-1)[inner].mean()
    still = np.linalg.norm(gt, axis=-1)[inner].mean()
    print(f"{method}: EPE {epe:.3f} px, zero flow {still:.3f} px")
    assert epe < 0.5 * still


def test_consistency_mask_rejects_pixels_the_tool_occludes(demo, tmp_path):
    """Tissue whose true target lies well inside the tool in the next frame has no match."""
    with_masks = flow_for_scene(load_scene(demo), progress=False, cache_dir=tmp_path)
    fb_only = flow_for_scene(load_scene(demo, use_masks=False), progress=False, cache_dir=tmp_path)
    scene = load_scene(demo)
    n_occ = rej_masked = rej_fb_occ = 0
    n_other = rej_fb_other = 0
    for k, pair in with_masks.items():
        if pair.dst != k + 1:
            continue
        gt = _gt(demo, k)
        u, v = _grid(*gt.shape[:2])
        core = cv2.erode((scene.frames[k + 1].mask == 0).astype(np.uint8), np.ones((3, 3), np.uint8))
        lands_on_tool = cv2.remap(core.astype(np.float32), u + gt[..., 0], v + gt[..., 1],
                                  cv2.INTER_NEAREST, borderValue=0) > 0
        tissue = scene.frames[k].mask > 0
        occ, other = tissue & lands_on_tool, tissue & ~lands_on_tool
        n_occ += occ.sum()
        n_other += other.sum()
        rej_masked += (pair.valid[occ] == 0).sum()
        rej_fb_occ += (fb_only[k].valid[occ] == 0).sum()
        rej_fb_other += (fb_only[k].valid[other] == 0).sum()
    assert n_occ > 200                     # the scene really has occlusions to test on
    rate_occ, rate_other = rej_fb_occ / n_occ, rej_fb_other / n_other
    print(f"{n_occ} occluded tissue pixels: valid mask rejects {100 * rej_masked / n_occ:.1f}%; "
          f"forward-backward alone rejects {100 * rate_occ:.1f}% (vs {100 * rate_other:.1f}% of other tissue)")
    assert rej_masked == n_occ
    # without masks the forward-backward test is the only defence: it must single out occlusions
    # (measured: ~15x more rejections than elsewhere)
    assert rate_occ > 5 * rate_other


def test_forward_backward_rule_on_constructed_flows():
    h, w = 40, 50
    fw = np.zeros((h, w, 2), np.float32)
    fw[...] = (3.0, 1.0)
    bw = -fw.copy()
    bw[10:20, 20:30] = (5.0, 0.0)                 # an occluder in frame k' moving its own way
    ok = fb_consistent(fw, bw)
    u, v = _grid(h, w)
    tx, ty = u + 3, v + 1
    hits_occluder = (tx >= 19) & (tx <= 30) & (ty >= 9) & (ty <= 20)   # incl. bilinear neighbours
    clean = ~hits_occluder & (tx <= w - 1) & (ty <= h - 1)
    assert ok[clean].all()
    assert not ok[(tx >= 21) & (tx <= 28) & (ty >= 11) & (ty <= 18)].any()
    assert not ok[tx > w - 1].any() and not ok[ty > h - 1].any()       # leaves the image
    # thresholds: |d|^2 < 0.01 (|f|^2 + |b|^2) + 0.5
    def check(f, b):
        return bool(fb_consistent(np.full((h, w, 2), f, np.float32), np.full((h, w, 2), b, np.float32))[20, 20])
    assert check((0, 0), (0.5, 0))             # 0.25 < 0.5025
    assert not check((0, 0), (0.6, 0.6))       # 0.72 > 0.5072
    assert check((20, 0), (-18.5, 0))          # 2.25 < 0.01 * (400 + 342.25) + 0.5 = 7.92
    assert not check((20, 0), (-17, 0))        # 9 > 0.01 * (400 + 289) + 0.5 = 7.39


def test_valid_mask_excludes_tool_pixels_in_either_frame():
    h, w = 30, 30
    fw = np.zeros((h, w, 2), np.float32)
    m0 = np.ones((h, w), np.float32)
    m1 = np.ones((h, w), np.float32)
    m0[5:10, 5:10] = 0                         # tool in frame k
    m1[20:25, 20:25] = 0                       # tool in frame k'
    valid = valid_mask(fw, fw, m0, m1)
    grown = flow_mod.TOOL_MARGIN
    assert not valid[5 - grown:10 + grown, 5 - grown:10 + grown].any()
    assert not valid[20 - grown:25 + grown, 20 - grown:25 + grown].any()
    assert valid[15, 15] == 1 and valid[0, 29] == 1
    shifted = np.zeros((h, w, 2), np.float32)
    shifted[..., 0] = 8.0                      # pixels of row 22 at x = 12..16 land on the tool
    v2 = valid_mask(shifted, -shifted, None, m1)
    assert not v2[22, 12:17].any() and v2[22, 5] == 1


def _counting(monkeypatch):
    calls = []
    real = flow_mod._estimate

    def counted(est, a, b):
        calls.append(1)
        return real(est, a, b)
    monkeypatch.setattr(flow_mod, "_estimate", counted)
    return calls


def test_cache_is_reused_and_invalidated(small, tmp_path, monkeypatch):
    calls = _counting(monkeypatch)
    scene = load_scene(small)
    n_pairs = len(training_pairs(scene))
    first = flow_for_scene(scene, progress=False, cache_dir=tmp_path)
    assert first.computed and len(calls) == 2 * n_pairs          # both directions
    assert first.cache_path.parent == tmp_path and (first.cache_path / "manifest.json").is_file()
    second = flow_for_scene(load_scene(small), progress=False, cache_dir=tmp_path)
    assert not second.computed and len(calls) == 2 * n_pairs     # nothing recomputed
    for k in first:
        assert np.array_equal(first[k].flow, second[k].flow) and np.array_equal(first[k].valid, second[k].valid)
        assert np.array_equal(first[k].flow_bw, second[k].flow_bw)
    # a changed frame gives a new key
    changed = load_scene(small)
    changed.frames[2].image = np.clip(changed.frames[2].image + 0.02, 0, 1)
    third = flow_for_scene(changed, progress=False, cache_dir=tmp_path)
    assert third.computed and third.cache_path != first.cache_path and len(calls) == 4 * n_pairs
    # so does another method or a changed mask
    calls.clear()
    assert flow_for_scene(scene, method="dis", progress=False, cache_dir=tmp_path).computed is False
    masked = load_scene(small)
    masked.frames[0].mask[:4] = 0
    assert flow_for_scene(masked, progress=False, cache_dir=tmp_path).computed
    # a damaged entry is recomputed and replaced
    victim = next(first.cache_path.glob("*.npz"))
    victim.write_bytes(b"broken")
    again = flow_for_scene(scene, progress=False, cache_dir=tmp_path)
    assert again.computed and again.cache_path == first.cache_path
    assert np.array_equal(again[0].flow, first[0].flow)
    assert not flow_for_scene(scene, progress=False, cache_dir=tmp_path).computed


def test_estimation_size_keeps_the_aspect_under_the_pixel_budget():
    assert flow_mod.estimation_size(640, 512, 0) == (640, 512)
    assert flow_mod.estimation_size(640, 512, 640 * 512) == (640, 512)
    assert flow_mod.estimation_size(640, 512, 320 * 256) == (320, 256)
    w, h = flow_mod.estimation_size(1280, 1024, 100_000)
    assert w * h <= 100_000 and abs(w / h - 1.25) < 0.01 and (w + 1) * (h + 1) > 100_000


def test_flow_estimated_on_smaller_frames_is_scaled_to_the_frame(demo, tmp_path, monkeypatch):
    """max_pixels: the estimator sees area-averaged frames of the budget's size, and the flow comes
    back at the frame's size in the frame's pixels, as computing it by hand gives; the cache keeps
    the two apart."""
    seen = []
    real = flow_mod._estimate

    def spy(est, a, b):
        seen.append(a.shape)
        return real(est, a, b)
    monkeypatch.setattr(flow_mod, "_estimate", spy)
    scene = load_scene(demo)                                           # 160x128
    full = flow_for_scene(scene, progress=False, cache_dir=tmp_path)
    half = flow_for_scene(scene, progress=False, cache_dir=tmp_path, max_pixels=80 * 64)
    assert half.computed and half.cache_path != full.cache_path
    assert set(seen[:len(seen) // 2]) == {(128, 160)} and set(seen[len(seen) // 2:]) == {(64, 80)}
    k = next(iter(half))
    p = half[k]
    grey = [cv2.resize(flow_mod.to_grey8(scene.frames[i].image), (80, 64), interpolation=cv2.INTER_AREA)
            for i in (p.src, p.dst)]
    small_flow = flow_mod._make_estimator("dis").calc(grey[0], grey[1], None)
    by_hand = cv2.resize(small_flow, (160, 128), interpolation=cv2.INTER_LINEAR) * 2.0
    assert p.flow.shape == (128, 160, 2) and p.valid.shape == (128, 160)
    np.testing.assert_allclose(p.flow, by_hand, atol=1e-5)
    # a coarser estimate of the same ~1 px motion stays close to the full-size one
    assert np.abs(p.flow - full[k].flow)[p.valid > 0].mean() < 0.5
    # the budget at or above the frame's size is the frame's own estimate, from the same cache entry
    seen.clear()
    same = flow_for_scene(scene, progress=False, cache_dir=tmp_path, max_pixels=160 * 128)
    assert not same.computed and same.cache_path == full.cache_path and not seen


def test_default_cache_root_is_outside_the_scene(small, tmp_path, monkeypatch):
    monkeypatch.setenv("ENDOWAVE_CL_CACHE", str(tmp_path / "c"))
    r = flow_for_scene(load_scene(small), progress=False)
    assert r.cache_path.parent == tmp_path / "c" / "flow"
    monkeypatch.delenv("ENDOWAVE_CL_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "x"))
    assert flow_mod.default_cache_root() == tmp_path / "x" / "endowave-cl" / "flow"
    no_cache = flow_for_scene(load_scene(small), progress=False, cache=False)
    assert no_cache.cache_path is None and no_cache.computed
    assert not (tmp_path / "x").exists()


def test_flo_and_npy_files(tmp_path):
    rng = np.random.default_rng(0)
    flow = rng.normal(size=(7, 11, 2)).astype(np.float32)
    write_flo(tmp_path / "a.flo", flow)
    assert np.array_equal(read_flo(tmp_path / "a.flo"), flow)
    assert np.array_equal(cv2.readOpticalFlow(str(tmp_path / "a.flo")), flow)   # OpenCV agrees
    cv2.writeOpticalFlow(str(tmp_path / "b.flo"), flow)
    assert np.array_equal(read_flow_file(tmp_path / "b.flo"), flow)
    np.save(tmp_path / "c.npy", flow.astype(np.float64))
    got = read_flow_file(tmp_path / "c.npy")
    assert got.dtype == np.float32 and np.allclose(got, flow)
    data = (tmp_path / "a.flo").read_bytes()
    (tmp_path / "t.flo").write_bytes(data[:-8])
    with pytest.raises(DataError, match=r"t\.flo.*truncated"):
        read_flow_file(tmp_path / "t.flo")
    assert data[:4] == b"PIEH"                           # the magic, as bytes
    (tmp_path / "m.flo").write_bytes(b"XXXX" + data[4:])
    with pytest.raises(DataError, match=r"m\.flo: not a \.flo file"):
        read_flow_file(tmp_path / "m.flo")
    np.save(tmp_path / "s.npy", np.zeros((4, 5, 3)))
    with pytest.raises(DataError, match=r"s\.npy: expected flow of shape"):
        read_flow_file(tmp_path / "s.npy")
    (tmp_path / "x.png").write_bytes(b"")
    with pytest.raises(DataError, match="unknown flow file type"):
        read_flow_file(tmp_path / "x.png")


def test_user_flow_is_used_instead_of_computing(small, tmp_path, monkeypatch):
    d = tmp_path / "scene"
    shutil.copytree(small, d)
    scene = load_scene(d)
    (d / "flow").mkdir()
    pairs = training_pairs(scene)
    const = np.zeros((scene.height, scene.width, 2), np.float32)
    const[..., 0] = 1.0
    for j, (k, k2) in enumerate(pairs):
        a, b = scene.frames[k].name, scene.frames[k2].name
        if j % 2:
            write_flo(d / "flow" / f"{a}_{b}.flo", const)
        else:
            np.save(d / "flow" / f"{a}_{b}.npy", const)
    np.save(d / "flow" / f"{scene.frames[pairs[0][1]].name}_{scene.frames[pairs[0][0]].name}.npy", -const)
    calls = _counting(monkeypatch)
    result = flow_for_scene(load_scene(d), progress=False, cache_dir=tmp_path / "cache")
    assert result.method == "user" and not calls and not (tmp_path / "cache").exists()
    assert set(result) == {k for k, _ in pairs}
    for k, pair in result.items():
        assert np.array_equal(pair.flow, const)
    first = result[pairs[0][0]]
    assert first.valid_bw.any() and np.array_equal(first.flow_bw, -const)   # backward given
    assert not result[pairs[1][0]].valid_bw.any()                            # backward absent
    # a downscaled scene gets the flow resized and its vectors halved
    half = flow_for_scene(load_scene(d, downscale=2), progress=False)
    assert half[pairs[0][0]].flow.shape == (scene.height // 2, scene.width // 2, 2)
    assert np.allclose(half[pairs[0][0]].flow[..., 0], 0.5)
    # a missing pair is an error naming the folder and the expected file
    (d / "flow" / f"{scene.frames[pairs[1][0]].name}_{scene.frames[pairs[1][1]].name}.flo").unlink()
    with pytest.raises(DataError, match=r"flow: no 000002_000003\.npy or \.flo"):
        flow_for_scene(load_scene(d), progress=False)
    write_flo(d / "flow" / "000002_000003.flo", np.zeros((10, 10, 2), np.float32))
    with pytest.raises(DataError, match=r"000002_000003\.flo: flow is 10x10"):
        flow_for_scene(load_scene(d), progress=False)


def test_unknown_method(small):
    with pytest.raises(DataError, match="unknown flow method 'gmflow'"):
        flow_for_scene(load_scene(small), method="gmflow", cache=False)


def test_cli_flow(small, tmp_path, capsys):
    args = ["flow", str(small), "--cache-dir", str(tmp_path), "--no-progress"]
    assert cli_main(args) == 0
    out = capsys.readouterr().out
    assert "4 pairs (dis_fine), computed" in out and "end-point error vs gt_flow" in out   # flow_method's
    assert cli_main(args) == 0
    assert "reused from cache" in capsys.readouterr().out
    assert cli_main(["flow", str(tmp_path / "missing"), "--no-progress"]) == 1
    assert "scene folder not found" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli_main(["flow", str(small), "--method", "gmflow"])
