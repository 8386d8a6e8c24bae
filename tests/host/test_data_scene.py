"""Loader for the EndoNeRF layout: synthetic scene, shared real frames, downscale, poses, intrinsics."""
from __future__ import annotations

import json

import numpy as np
import pytest

from endowave_cl.data import load_scene, split_indices
from endowave_cl.data.llff import Q_LLFF_FROM_CV, llff_to_viewmat
from endowave_cl.data.synth import FOCAL_PER_WIDTH, make_synthetic_scene

W, H, N = 64, 48, 10


@pytest.fixture(scope="module")
def synth_scene(tmp_path_factory):
    return make_synthetic_scene(tmp_path_factory.mktemp("syn") / "scene", width=W, height=H, frames=N, seed=3)


def test_synthetic_scene_loads_with_shapes_times_split_camera(synth_scene):
    scene = load_scene(synth_scene, depth_percentiles=None)
    assert (scene.width, scene.height, len(scene.frames)) == (W, H, N)
    assert scene.has_depth and scene.has_masks
    assert scene.test_indices == [1, 9] and scene.train_indices == [0, 2, 3, 4, 5, 6, 7, 8]
    assert scene.summary().startswith(f"{N} frames, {W}x{H}, depth, masks: depth loss on")
    for i, fr in enumerate(scene.frames):
        assert fr.index == i and fr.time == pytest.approx(i / (N - 1))
        assert fr.image.shape == (H, W, 3) and fr.image.dtype == np.float32
        assert 0 <= fr.image.min() and fr.image.max() <= 1
        assert fr.depth.shape == (H, W) and fr.mask.shape == (H, W)
        assert set(np.unique(fr.mask)) <= {0.0, 1.0} and 0 < fr.mask.mean() < 1  # tool visible
        cam = fr.camera
        assert np.allclose(cam.viewmat, np.eye(4))
        assert (cam.fx, cam.cx, cam.cy) == (pytest.approx(FOCAL_PER_WIDTH * W), W / 2, H / 2)
        # the camera convention: each pixel's ground-truth 3D point projects to its pixel centre
        pts = np.load(synth_scene / "gt_points" / f"{i:06d}.npy")             # [H, W, 3]
        px = cam.fx * pts[..., 0] / pts[..., 2] + cam.cx
        py = cam.fy * pts[..., 1] / pts[..., 2] + cam.cy
        u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
        assert np.abs(px - u).max() < 1e-3 and np.abs(py - v).max() < 1e-3
        # depth in scene units: file units (scene.json depth_scale) times world_scale, equal to the
        # points' z up to quantisation
        assert np.abs(fr.depth / scene.world_scale - pts[..., 2]).max() <= 0.5e-3 + 1e-5
        assert scene.near < fr.depth.min() and fr.depth.max() < scene.far


def test_depth_percentile_clipping_keeps_invalid_zero(synth_scene):
    scene = load_scene(synth_scene, depth_percentiles=(10, 90))
    d = scene.frames[0].depth
    raw = load_scene(synth_scene, depth_percentiles=None).frames[0].depth
    lo, hi = np.percentile(raw, [10, 90])
    assert d.min() == pytest.approx(lo) and d.max() == pytest.approx(hi)
    from endowave_cl.data.scene import clip_depth
    holes = raw.copy()
    holes[:5] = 0
    assert np.all(clip_depth(holes, (10, 90))[:5] == 0)


def test_downscale(synth_scene):
    full = load_scene(synth_scene, depth_percentiles=None)
    half = load_scene(synth_scene, downscale=2, depth_percentiles=None)
    assert (half.width, half.height) == (W // 2, H // 2)
    f, h = full.frames[4], half.frames[4]
    assert h.image.shape == (H // 2, W // 2, 3)
    assert h.camera.fx == pytest.approx(f.camera.fx / 2) and h.camera.cx == pytest.approx(W / 4)
    blocks = f.image.reshape(H // 2, 2, W // 2, 2, 3).mean(axis=(1, 3))
    assert np.allclose(h.image, blocks, atol=1e-5)
    # a half-size mask pixel is tissue only where all four full-size pixels were
    tissue_blocks = f.mask.reshape(H // 2, 2, W // 2, 2).min(axis=(1, 3))
    assert np.array_equal(h.mask, tissue_blocks)
    assert set(np.unique(h.depth)) <= set(np.unique(f.depth))   # nearest: no mixed depths
    assert "downscale 2" in half.summary()


def test_shared_real_frames(pulling_scene):
    scene = load_scene(pulling_scene)
    assert len(scene.frames) == 63 and (scene.width, scene.height) == (640, 512)
    assert not scene.has_depth and not scene.has_masks
    assert scene.summary().startswith("63 frames, 640x512, no depth, no masks: depth loss off")
    assert scene.test_indices == [1, 9, 17, 25, 33, 41, 49, 57]
    fr = scene.frames[62]
    assert fr.time == 1.0 and fr.depth is None and fr.mask is None
    cam = fr.camera
    assert (cam.fx, cam.cx, cam.cy) == (pytest.approx(569.46820041), 320.0, 256.0)
    # identity pose -> camera at the origin looking down +z: a point on +z projects to the centre
    p = cam.viewmat @ np.array([0.0, 0.0, 0.5 * (scene.near + scene.far), 1.0])
    assert p[2] > 0 and np.allclose(p[:2], 0) and np.allclose(cam.campos, 0)
    assert scene.far > scene.near >= 0


def test_llff_pose_conversion_matches_axis_definition():
    rng = np.random.default_rng(0)
    A, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    R = A * np.sign(np.linalg.det(A))           # a rotation: LLFF columns (down, right, back) in world
    t = rng.standard_normal(3)
    view = llff_to_viewmat(np.concatenate([R, t[:, None]], 1)).astype(np.float64)
    # a point `down` a, `right` b, `ahead` d of the LLFF camera ...
    a, b, d = 0.3, -0.7, 2.5
    x_world_llff = R @ np.array([a, b, -d]) + t
    x_world = Q_LLFF_FROM_CV.T @ x_world_llff          # ... in our (relabelled) world axes
    x_cam = view[:3, :3] @ x_world + view[:3, 3]
    assert np.allclose(x_cam, [b, a, d], atol=1e-5)    # OpenCV: x right, y down, z forward
    assert np.allclose(llff_to_viewmat(np.eye(3, 4)), np.eye(4))


def _rewrite_poses(scene_dir, fn):
    arr = np.load(scene_dir / "poses_bounds.npy")
    np.save(scene_dir / "poses_bounds.npy", fn(arr))


def test_stereomis_hwf_is_detected_and_can_be_overridden(synth_scene, tmp_path):
    import shutil
    d = tmp_path / "stereomis"
    shutil.copytree(synth_scene, d)
    info = json.loads((d / "scene.json").read_text())
    del info["hwf_layout"]
    (d / "scene.json").write_text(json.dumps(info))
    cy, cx, f = 22.5, 33.0, 50.0

    def stereomis(arr):
        arr = arr.copy()
        arr[:, 4], arr[:, 9], arr[:, 14] = cy, cx, f    # hwf column = (cy, cx, f)
        arr[:, 15], arr[:, 16] = 0.03, 250.0
        return arr
    _rewrite_poses(d, stereomis)
    scene = load_scene(d)                                # auto: (cy, cx) is not the image size
    cam = scene.frames[0].camera
    assert (cam.fx, cam.cx, cam.cy) == (f, cx, cy) and scene.hwf_layout == "cy_cx_f"
    assert (scene.near / scene.world_scale, scene.far / scene.world_scale) == (pytest.approx(0.03), pytest.approx(250.0))
    half = load_scene(d, downscale=2).frames[0].camera
    assert (half.cx, half.cy) == (cx / 2, cy / 2)
    with pytest.raises(Exception, match="poses_bounds.npy.*images are"):
        load_scene(d, hwf_layout="hwf")                 # explicit override is obeyed
    info["hwf_layout"] = "hwf"                          # and the flag in scene.json too
    (d / "scene.json").write_text(json.dumps(info))
    with pytest.raises(Exception, match="images are"):
        load_scene(d)


def test_split_indices():
    train, test = split_indices(17)
    assert test == [1, 9] and sorted(train + test) == list(range(17))


def _with_depth_units(src, dst, factor):
    """A copy of the scene src whose depth files and bounds are in units factor times smaller."""
    import shutil
    shutil.copytree(src, dst)
    info = json.loads((dst / "scene.json").read_text())
    info["depth_scale"] = info["depth_scale"] * factor
    (dst / "scene.json").write_text(json.dumps(info))
    _rewrite_poses(dst, lambda a: np.concatenate([a[:, :15], a[:, 15:] * factor], 1))
    return dst


def test_scene_units_do_not_depend_on_the_files_units(synth_scene, tmp_path):
    from endowave_cl.data.scene import SCENE_DEPTH
    a = load_scene(synth_scene)
    b = load_scene(_with_depth_units(synth_scene, tmp_path / "x30", 30.0))
    assert b.world_scale == pytest.approx(a.world_scale / 30.0, rel=1e-6)
    assert (b.near, b.far) == (pytest.approx(a.near, rel=1e-6), pytest.approx(a.far, rel=1e-6))
    for fa, fb in zip(a.frames, b.frames):
        np.testing.assert_allclose(fb.depth, fa.depth, rtol=1e-6)
    # the training frames' median depth sits at SCENE_DEPTH, whatever the files' units
    d = np.concatenate([a.frames[i].depth[a.frames[i].depth > 0] for i in a.train_indices])
    assert np.median(d) == pytest.approx(SCENE_DEPTH, rel=1e-6)
    # ignoring the depth maps does not change the units (a run and its evaluation agree)
    assert load_scene(synth_scene, use_depth=False).world_scale == a.world_scale
    assert load_scene(synth_scene, downscale=2).world_scale == a.world_scale


def test_scene_without_depth_puts_its_prior_plane_at_scene_depth(synth_scene, tmp_path):
    import shutil
    from endowave_cl.data.scene import SCENE_DEPTH
    from endowave_cl.train.init import prior_depth
    dst = tmp_path / "nodepth"
    shutil.copytree(synth_scene, dst)
    shutil.rmtree(dst / "depth")
    _rewrite_poses(dst, lambda a: np.concatenate([a[:, :15], np.tile([0.0, 500.0], (len(a), 1))], 1))
    s = load_scene(dst)
    assert s.world_scale == pytest.approx(SCENE_DEPTH / np.sqrt(0.5 * 500.0))
    assert prior_depth(s.frames, s.train_indices, s.near, s.far) == pytest.approx(SCENE_DEPTH)


def test_set_world_scale_scales_depth_bounds_and_camera_translations(synth_scene, tmp_path):
    dst = tmp_path / "moved"
    import shutil
    shutil.copytree(synth_scene, dst)
    # a camera translated along the LLFF axes: its centre must scale with the world
    _rewrite_poses(dst, lambda a: np.concatenate([a[:, :3], a[:, 3:4] + 0.25, a[:, 4:]], 1))
    raw = load_scene(dst, world_scale=1.0)
    s = load_scene(dst, world_scale=2.5)
    assert s.world_scale == 2.5 and s.near == pytest.approx(2.5 * raw.near)
    for fr, fs in zip(raw.frames, s.frames):
        np.testing.assert_allclose(fs.depth, 2.5 * fr.depth, rtol=1e-6)
        np.testing.assert_allclose(fs.camera.campos, 2.5 * fr.camera.campos, rtol=1e-5, atol=1e-6)
        np.testing.assert_array_equal(fs.camera.viewmat[:3, :3], fr.camera.viewmat[:3, :3])
    assert np.abs(raw.frames[0].camera.campos).max() > 0.1
    s.set_world_scale(1.0)
    np.testing.assert_allclose(s.frames[3].depth, raw.frames[3].depth, rtol=1e-6)
    from endowave_cl.errors import DataError
    with pytest.raises(DataError, match="world_scale must be a positive number"):
        s.set_world_scale(0.0)
