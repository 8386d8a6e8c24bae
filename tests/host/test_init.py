"""Initial Gaussians from fake frames (train/init.py)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
import pytest

from endowave_cl.camera import Camera
from endowave_cl.errors import EndowaveError
from endowave_cl.train.init import INIT_OPACITY, SH_C0, TIME_SCALE_FRAMES, init_gaussians


@dataclass
class Frame:
    image: np.ndarray
    depth: Optional[np.ndarray]
    mask: Optional[np.ndarray]
    camera: Camera
    time: float


def _viewmat(angle, t):
    c, s = math.cos(angle), math.sin(angle)
    V = np.eye(4)
    V[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    V[:3, 3] = t
    return V


def _frames(n=4, H=12, W=16, depth=True, mask=True, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        cam = Camera(20.0, 22.0, 7.5, 6.0, W, H, _viewmat(0.1 * i, [0.1 * i, -0.2, 0.3]))
        d = rng.uniform(2, 5, (H, W)).astype(np.float32) if depth else None
        if d is not None:
            d[rng.random((H, W)) < 0.2] = 0  # invalid pixels
        m = (rng.random((H, W)) > 0.3).astype(np.float32) if mask else None
        out.append(Frame(rng.random((H, W, 3)).astype(np.float32), d, m, cam, i / (n - 1)))
    return out


def _project(frame, xyz):
    pc = np.c_[xyz, np.ones(len(xyz))] @ frame.camera.viewmat.astype(np.float64).T
    c = frame.camera
    return c.fx * pc[:, 0] / pc[:, 2] + c.cx, c.fy * pc[:, 1] / pc[:, 2] + c.cy, pc[:, 2]


def test_points_project_back_onto_their_source_pixels():
    frames = _frames()
    train = [0, 1, 3]
    g = init_gaussians(frames, train, 0.1, 10.0, max_points=10 ** 6, seed=0)
    n_valid = sum(int(((frames[k].depth > 0) & (frames[k].mask > 0.5)).sum()) for k in train)
    assert len(g) == n_valid  # no subsampling: every supervised pixel
    times = g.means[:, 3]
    np.testing.assert_allclose(np.unique(times), [frames[k].time for k in train], rtol=1e-6)
    for k in train:
        f = frames[k]
        sel = np.isclose(times, f.time)
        u, v, z = _project(f, g.means[sel, :3].astype(np.float64))
        iu, iv = np.floor(u).astype(int), np.floor(v).astype(int)
        np.testing.assert_allclose(u - iu, 0.5, atol=1e-3)  # pixel centres
        np.testing.assert_allclose(v - iv, 0.5, atol=1e-3)
        np.testing.assert_allclose(z, f.depth[iv, iu], rtol=1e-5)
        assert np.all(f.mask[iv, iu] > 0.5)
        np.testing.assert_allclose(0.5 + SH_C0 * g.sh[sel, 0, 0, :], f.image[iv, iu], atol=1e-5)
        # footprint scale: depth / f (stride 1)
        want = z * 0.5 * (1 / f.camera.fx + 1 / f.camera.fy)
        np.testing.assert_allclose(np.exp(g.scales[sel, 0]), want, rtol=1e-5)
    assert np.all(g.sh[:, 1:] == 0) and np.all(g.sh[:, 0, 1:] == 0)
    np.testing.assert_array_equal(g.quat_l, np.tile([1, 0, 0, 0], (len(g), 1)))
    np.testing.assert_array_equal(g.quat_r, g.quat_l)
    np.testing.assert_allclose(1 / (1 + np.exp(-g.opacity)), INIT_OPACITY, rtol=1e-5)
    spacing = 0.5  # train times 0, 1/3, 1: spacings 1/3 and 2/3, median 1/2
    np.testing.assert_allclose(np.exp(g.scales[:, 3]), TIME_SCALE_FRAMES * spacing, rtol=1e-5)


def test_subsampling_count_stride_and_seed():
    frames = _frames()
    g = init_gaussians(frames, [0, 1, 2, 3], 0.1, 10.0, max_points=100, seed=3)
    n_valid = sum(int(((f.depth > 0) & (f.mask > 0.5)).sum()) for f in frames)
    assert len(g) == 100
    # scales carry the stride: spacing of the Gaussians seen at one time (marginal above one half)
    t, sigma_t = g.means[:, 3].astype(np.float64), float(np.exp(g.scales[0, 3]))
    visible = np.mean([np.mean(np.abs(t - f.time) <= 1.18 * sigma_t) for f in frames])
    assert 0 < visible < 1
    stride = max(1.0, math.sqrt(n_valid / len(frames) / (100 * visible)))
    assert stride > 1
    f0 = frames[0]
    sel = np.isclose(g.means[:, 3], f0.time)
    _, _, z = _project(f0, g.means[sel, :3].astype(np.float64))
    want = z * 0.5 * (1 / f0.camera.fx + 1 / f0.camera.fy) * stride
    np.testing.assert_allclose(np.exp(g.scales[sel, 0]), want, rtol=1e-5)
    g2 = init_gaussians(frames, [0, 1, 2, 3], 0.1, 10.0, max_points=100, seed=3)
    np.testing.assert_array_equal(g.means, g2.means)
    g3 = init_gaussians(frames, [0, 1, 2, 3], 0.1, 10.0, max_points=100, seed=4)
    assert not np.array_equal(g.means, g3.means)


def test_no_depth_prior_is_a_fronto_parallel_surface_covering_the_view():
    frames = _frames(depth=False, mask=False)
    near, far = 0.5, 8.0
    g = init_gaussians(frames, [0, 2, 3], near, far, max_points=10 ** 6, seed=0, sh_degree=1, nt=1)
    assert g.sh.shape[1:] == (2, 4, 3) and g.phase.shape[1] == 2
    H, W = frames[0].image.shape[:2]
    assert len(g) == 3 * H * W
    for k in (0, 2, 3):
        f = frames[k]
        sel = np.isclose(g.means[:, 3], f.time)
        u, v, z = _project(f, g.means[sel, :3].astype(np.float64))
        np.testing.assert_allclose(z, math.sqrt(near * far), rtol=1e-5)
        assert u.min() < 1 and u.max() > W - 1 and v.min() < 1 and v.max() > H - 1
    # a mixed scene: frames without depth use the median of the measured depths
    mixed = _frames(depth=True, mask=False)
    mixed[1].depth = None
    g = init_gaussians(mixed, [0, 1], near, far, max_points=10 ** 6)
    sel = np.isclose(g.means[:, 3], mixed[1].time)
    _, _, z = _project(mixed[1], g.means[sel, :3].astype(np.float64))
    d0 = mixed[0].depth
    np.testing.assert_allclose(z, np.median(d0[d0 > 0]), rtol=1e-5)


def test_bad_inputs():
    frames = _frames()
    for f in frames:
        f.mask[:] = 0
    with pytest.raises(EndowaveError, match="no training pixel"):
        init_gaussians(frames, [0, 1], 0.1, 10, 10)
    with pytest.raises(EndowaveError, match="max_points"):
        init_gaussians(_frames(), [0], 0.1, 10, 0)
    with pytest.raises(EndowaveError, match="no training frames"):
        init_gaussians(_frames(), [], 0.1, 10, 5)
    with pytest.raises(EndowaveError, match="bounds"):
        init_gaussians(_frames(depth=False), [0], 0.1, -1.0, 5)
    g = init_gaussians(_frames(depth=False, mask=False), [0], 0.0, 10.0, 10 ** 6)  # near 0: far / 1000
    f = _frames(depth=False, mask=False)[0]
    np.testing.assert_allclose(_project(f, g.means[:, :3].astype(np.float64))[2], math.sqrt(0.01 * 10), rtol=1e-5)
