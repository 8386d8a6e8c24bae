"""Synthetic scene generator: ground truth consistency, highlights, occlusion, atomic output, CLI."""
from __future__ import annotations

import json
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest

from endowave_cl.cli import main as cli_main
from endowave_cl.data import load_scene
from endowave_cl.data import synth
from endowave_cl.data.synth import make_synthetic_scene
from endowave_cl.errors import DataError

W, H, N = 96, 80, 8


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    return make_synthetic_scene(tmp_path_factory.mktemp("syn") / "scene", width=W, height=H, frames=N, seed=5)


def test_files_and_metadata(scene_dir):
    for sub, n in (("images", N), ("depth", N), ("masks", N), ("gt_points", N), ("gt_flow", N - 1)):
        assert len(list((scene_dir / sub).iterdir())) == n, sub
    info = json.loads((scene_dir / "scene.json").read_text())
    assert info["depth_scale"] == synth.DEPTH_SCALE
    assert info["params"] == {"width": W, "height": H, "frames": N, "seed": 5, "deformation": 1.0}
    raw = cv2.imread(str(scene_dir / "depth" / "000000.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16
    m = cv2.imread(str(scene_dir / "masks" / "000000.png"), cv2.IMREAD_UNCHANGED)
    assert set(np.unique(m)) == {0, 255}                 # EndoNeRF convention: 255 on the tool
    assert not any(p.name.startswith(".") for p in scene_dir.parent.iterdir())   # no temp left


def test_tissue_depth_range_and_bounds(scene_dir):
    scene = load_scene(scene_dir, depth_percentiles=None)
    depth = np.stack([f.depth for f in scene.frames])            # [N, H, W]
    tissue = np.stack([f.mask for f in scene.frames]) > 0
    assert 3.0 < depth[tissue].min() and depth[tissue].max() < 6.5
    assert scene.near < depth.min() and depth.max() < scene.far < 8
    # the tool occludes: it is nearer than the tissue around it
    assert depth[~tissue].max() < np.median(depth[tissue])


def _warp_back(img1, flow):
    """Sample frame k+1 at p + flow(p): [H, W, 3]."""
    h, w = flow.shape[:2]
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return cv2.remap(img1, u + flow[..., 0], v + flow[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def test_ground_truth_flow_and_points_agree_with_images(scene_dir):
    scene = load_scene(scene_dir, depth_percentiles=None)
    errs_gt, errs_zero = [], []
    for k in range(N - 1):
        f0, f1 = scene.frames[k], scene.frames[k + 1]
        flow = np.load(scene_dir / "gt_flow" / f"{k:06d}.npy")          # [H, W, 2]
        u, v = np.meshgrid(np.arange(W), np.arange(H))
        tx = np.clip(np.round(u + flow[..., 0]).astype(int), 0, W - 1)
        ty = np.clip(np.round(v + flow[..., 1]).astype(int), 0, H - 1)
        keep = ((f0.mask > 0) & (f1.mask[ty, tx] > 0)
                & (u + flow[..., 0] > 1) & (u + flow[..., 0] < W - 2)
                & (v + flow[..., 1] > 1) & (v + flow[..., 1] < H - 2))
        errs_gt.append(np.abs(_warp_back(f1.image, flow) - f0.image)[keep].mean())
        errs_zero.append(np.abs(f1.image - f0.image)[keep].mean())
        # tool pixels: their flow is the projection of the rigidly moved tool point
        p0 = np.load(scene_dir / "gt_points" / f"{k:06d}.npy")
        assert np.isfinite(p0).all() and p0[..., 2].min() > 0
    gt, zero = float(np.mean(errs_gt)), float(np.mean(errs_zero))
    print(f"photometric error after warping with GT flow {gt:.4f}, without {zero:.4f}")
    # Warping with the true flow explains the images up to shading changes (highlights follow the
    # surface normal, brightness the inverse-square distance to the light, and 8 frames make the
    # per-frame deformation large) and bilinear resampling: clearly better than no motion.
    assert gt < 0.5 * zero


def test_ground_truth_flow_carries_the_texture():
    """Without shading, the albedo of frame k+1 sampled at p + flow equals that of frame k."""
    sc = synth._Scene(W, H, N, 5, 1.0)
    inner = (slice(5, -5), slice(5, -5))       # away from the border (texture reflect padding)
    for k in range(3):
        t0, t1 = k / (N - 1), (k + 1) / (N - 1)
        a0, a1 = sc.tissue(t0)[0], sc.tissue(t1)[0]
        flow = sc.tissue_flow(t0, t1).astype(np.float32)
        err = np.abs(_warp_back(a1, flow) - a0)[inner].mean()
        still = np.abs(a1 - a0)[inner].mean()
        print(f"albedo error with GT flow {err:.4f}, without {still:.4f}")
        assert err < 0.2 * still and err < 0.01    # what is left is bilinear resampling


def test_deformation_zero_gives_static_tissue(tmp_path):
    d = make_synthetic_scene(tmp_path / "rigid", width=48, height=40, frames=4, deformation=0.0)
    s = load_scene(d)
    for k in range(3):
        flow = np.load(d / "gt_flow" / f"{k:06d}.npy")
        tissue = (s.frames[k].mask > 0)
        assert np.abs(flow[tissue]).max() < 1e-6
        assert np.abs(flow[~tissue]).max() > 0.1          # the tool still moves
    moving = np.load(make_synthetic_scene(tmp_path / "soft", width=48, height=40, frames=4) / "gt_flow" / "000000.npy")
    assert np.abs(moving).max() > 0.5


def test_specular_highlights_are_present(monkeypatch):
    sc = synth._Scene(W, H, N, 5, 1.0)
    rgb = sc.frame(2)[0]
    monkeypatch.setattr(synth, "TISSUE_SPECULAR", 0.0)
    matte = sc.frame(2)[0]
    spec = (rgb - matte).mean(-1)                          # [H, W] specular contribution
    frac = float((spec > 0.2).mean())
    print(f"highlight pixels: {100 * frac:.1f}%, max specular {spec.max():.2f}")
    assert spec.max() > 0.4 and 0.002 < frac < 0.2          # bright, but local
    # highlights are white (the specular term is added to every channel): green and blue, which
    # the red tissue leaves far from saturation, rise with them
    hi = spec > 0.2
    assert np.all((rgb - matte)[hi][:, 1:].min(-1) > 0.15)


def test_seed_is_deterministic(tmp_path):
    a = make_synthetic_scene(tmp_path / "a", width=32, height=24, frames=3, seed=7)
    b = make_synthetic_scene(tmp_path / "b", width=32, height=24, frames=3, seed=7)
    c = make_synthetic_scene(tmp_path / "c", width=32, height=24, frames=3, seed=8)
    img = lambda d: cv2.imread(str(d / "images" / "000001.png"))
    assert np.array_equal(img(a), img(b)) and not np.array_equal(img(a), img(c))


def test_more_frames_of_the_same_seed_keep_the_frames_at_their_times(tmp_path):
    """A scene generated again with F times as many intervals (frames = (n - 1) F + 1) has the same
    frames at the first one's times: research/fraction_eval.py scores a run between its frames on
    that scene (moved here from tests/test_fraction_eval.py)."""
    a = load_scene(make_synthetic_scene(tmp_path / "a", width=32, height=24, frames=4, seed=5))
    b = load_scene(make_synthetic_scene(tmp_path / "b", width=32, height=24, frames=7, seed=5),
                   world_scale=a.world_scale)
    for j, f in enumerate(a.frames):
        g = b.frames[2 * j]
        assert g.time == f.time
        np.testing.assert_array_equal(g.image, f.image)
        np.testing.assert_array_equal(g.depth, f.depth)
        np.testing.assert_array_equal(g.camera.viewmat, f.camera.viewmat)


def test_failed_generation_leaves_nothing(tmp_path, monkeypatch):
    def boom(self, i):
        raise RuntimeError("disk full")
    monkeypatch.setattr(synth._Scene, "frame", boom)
    with pytest.raises(RuntimeError):
        make_synthetic_scene(tmp_path / "out", width=32, height=24, frames=3)
    assert list(tmp_path.iterdir()) == []


def test_refuses_non_empty_out_unless_forced(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("precious")
    with pytest.raises(DataError, match="not empty"):
        make_synthetic_scene(out, width=32, height=24, frames=3)
    assert (out / "keep.txt").read_text() == "precious"
    make_synthetic_scene(out, width=32, height=24, frames=3, force=True)
    assert not (out / "keep.txt").exists() and (out / "poses_bounds.npy").is_file()


def test_cli_synth(tmp_path, capsys):
    out = tmp_path / "cli"
    assert cli_main(["synth", str(out), "--frames", "8", "--width", "48", "--height", "40", "--seed", "2"]) == 0
    assert "8 frames, 48x40, depth, masks" in capsys.readouterr().out
    assert cli_main(["synth", str(out), "--frames", "8"]) == 1             # non-empty, no --force
    assert "not empty" in capsys.readouterr().err
    assert cli_main(["synth", str(tmp_path / "x"), "--frames", "1"]) == 1
    assert "at least 2 frames" in capsys.readouterr().err


def test_demo_scene_is_quick_via_module_entry_point(tmp_path):
    start = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "endowave_cl", "synth", str(tmp_path / "demo")],
                       capture_output=True, text=True, timeout=120)
    took = time.perf_counter() - start
    print(f"demo 160x128x24 via CLI: {took:.1f} s")
    assert r.returncode == 0, r.stderr
    assert "24 frames, 160x128" in r.stdout
    assert took < 30      # a few seconds on 2 cores; the bound only catches pathologies
