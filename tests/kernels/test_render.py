"""The whole render op (project4d -> bin -> sort -> rasterize, and the adjoints) against the dense
torch reference (reference/render.py), which uses neither the tile lists nor the sort."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from conftest import small
from endowave_cl.camera import Camera
from endowave_cl.gaussians import PARAM_NAMES, Gaussians, upload
from endowave_cl.reference.render import render_ref
from endowave_cl.render import render, render_backward


def _camera(w, h):
    return Camera(fx=0.9 * w, fy=0.9 * w, cx=w / 2, cy=h / 2, width=w, height=h)


def _scene(n, seed, w, h):
    """Random Gaussians in view, plus some behind the camera, off-screen and temporally culled."""
    g = Gaussians.random(n, seed=seed, center=(0, 0, 3), spread=1.2, scale=0.06)
    rng = np.random.default_rng(seed)
    m = g.means.copy()
    m[: n // 10, 2] = -1.0                      # behind the camera
    m[n // 10: n // 5, 0] = 40.0                # far off-screen
    g.means = m
    g.scales[:, 3] = np.log(rng.uniform(0.05, 0.6, n)).astype(np.float32)
    return g


def _torch_params(g, requires_grad=False):
    return {k: torch.tensor(getattr(g, k), dtype=torch.float64, requires_grad=requires_grad) for k in PARAM_NAMES}


@pytest.mark.parametrize("n,seed,w,h", [(60, 0, 48, 40), (150, 1, 70, 37), (1, 2, 33, 17)])
@pytest.mark.parametrize("t_flow", [None, 0.6])
def test_render_matches_dense_reference(rt, n, seed, w, h, t_flow):
    g = _scene(n, seed, w, h)
    cam = _camera(w, h)
    out = render(rt, upload(rt, g), cam, 0.5, t_flow).host()
    with torch.no_grad():
        ref = render_ref(_torch_params(g), cam, 0.5, t_flow)
    for key in ("image", "depth", "flow", "alpha"):
        np.testing.assert_allclose(out[key], ref[key].numpy(), rtol=1e-4, atol=2e-4, err_msg=key)


def test_empty_scene_renders_nothing_and_has_empty_gradients(rt):
    g = Gaussians.empty()
    cam = _camera(40, 24)
    params = upload(rt, g)
    out = render(rt, params, cam, 0.3, 0.4)
    h = out.host()
    assert out.n_isect == 0 and np.all(h["alpha"] == 0) and np.all(h["image"] == 0)
    import pyopencl.array as cla
    grads = render_backward(rt, params, out, cla.zeros(rt.queue, (24, 40, 6), np.float32))
    assert all(v.size == 0 for v in grads.values())


def test_one_gaussian_covering_many_tiles(rt):
    g = Gaussians.random(1, seed=5, center=(0, 0, 2.0), spread=0.0, scale=0.4)
    g.means[0, 3] = 0.5
    cam = _camera(96, 80)
    out = render(rt, upload(rt, g), cam, 0.5)
    assert out.n_isect == out.tile_ranges.shape[0] == 6 * 5   # every tile
    with torch.no_grad():
        ref = render_ref(_torch_params(g), cam, 0.5)
    np.testing.assert_allclose(out.host()["image"], ref["image"].numpy(), rtol=1e-4, atol=1e-4)


@pytest.mark.oclgrind
@pytest.mark.parametrize("n,seed,w,h", [(small(80, 12), 3, small(52, 20), small(44, 18)), (small(200, 12), 4, small(64, 20), small(48, 18))])
def test_render_backward_matches_autograd_of_reference(rt, n, seed, w, h):
    g = _scene(n, seed, w, h)
    cam = _camera(w, h)
    params = upload(rt, g)
    t, t2 = 0.45, 0.55
    out = render(rt, params, cam, t, t2)
    rng = np.random.default_rng(seed)
    v_feat = rng.standard_normal((h, w, 6)).astype(np.float32)
    import pyopencl.array as cla
    grads = render_backward(rt, params, out, cla.to_device(rt.queue, v_feat))

    tp = _torch_params(g, requires_grad=True)
    ref = render_ref(tp, cam, t, t2)
    feats = torch.cat([ref["image"], ref["depth"][..., None], ref["flow"]], -1)
    (feats * torch.tensor(v_feat, dtype=torch.float64)).sum().backward()
    for name in PARAM_NAMES:
        got = grads["v_" + name].get().astype(np.float64)
        want = tp[name].grad.numpy()
        assert np.all(np.isfinite(got)), name
        scale = np.abs(want).max() + 1e-12
        np.testing.assert_allclose(got, want, rtol=2e-3, atol=2e-3 * scale, err_msg=name)


def test_densify_stats_are_accumulated(rt):
    import pyopencl.array as cla
    g = _scene(50, 7, 40, 32)
    cam = _camera(40, 32)
    params = upload(rt, g)
    out = render(rt, params, cam, 0.5)
    stats = {"grad_accum": cla.zeros(rt.queue, (50,), np.float32), "count": cla.zeros(rt.queue, (50,), np.int32),
             "max_radius": cla.zeros(rt.queue, (50,), np.float32)}
    v = cla.to_device(rt.queue, np.ones((32, 40, 6), np.float32))
    render_backward(rt, params, out, v, densify_stats=stats)
    visible = out.proj.radius.get() > 0
    assert np.array_equal(stats["count"].get() > 0, visible)
    assert np.all(stats["grad_accum"].get()[~visible] == 0)
    np.testing.assert_array_equal(stats["max_radius"].get()[visible], out.proj.radius.get()[visible])


def test_deterministic_backward_is_bit_identical(rt):
    import pyopencl.array as cla
    g = _scene(300, 9, 64, 48)
    cam = _camera(64, 48)
    params = upload(rt, g)
    v = cla.to_device(rt.queue, np.random.default_rng(0).standard_normal((48, 64, 6)).astype(np.float32))
    runs = []
    for _ in range(3):
        out = render(rt, params, cam, 0.5, 0.6)
        runs.append({k: a.get() for k, a in render_backward(rt, params, out, v, deterministic=True).items()})
    for k in runs[0]:
        assert np.array_equal(runs[0][k], runs[1][k]) and np.array_equal(runs[0][k], runs[2][k]), k
    out = render(rt, params, cam, 0.5, 0.6)
    free = render_backward(rt, params, out, v, deterministic=False)
    for k, a in free.items():   # the atomic mode computes the same gradients up to rounding
        np.testing.assert_allclose(a.get(), runs[0][k], rtol=1e-4, atol=1e-5 * (np.abs(runs[0][k]).max() + 1e-12))


def test_render_with_too_small_pair_buffers(rt):
    """The binning's pair buffers sized below the pair count (ops/binning.py PairCapacity): a checked
    render (the default) re-emits and gives the very bits of a render with room, forward and
    deterministic adjoint; an unchecked one says it overflowed."""
    import pyopencl.array as cla
    from endowave_cl.layout import tile_grid
    from endowave_cl.ops.binning import pair_capacity
    w, h = 70, 37
    g = _scene(150, 1, w, h)
    cam = _camera(w, h)
    params = upload(rt, g)
    v = cla.to_device(rt.queue, np.random.default_rng(2).standard_normal((h, w, 6)).astype(np.float32))
    policy = pair_capacity(rt, *tile_grid(w, h))

    def run(check):
        out = render(rt, params, cam, 0.5, 0.6, check=check)
        if out.overflowed:
            return out, None
        return out, {"features": out.features.get(), **{k: a.get() for k, a in
                     render_backward(rt, params, out, v, deterministic=True).items()}}
    _, want = run(True)
    m = render(rt, params, cam, 0.5).n_isect
    assert m > 2
    policy.capacity = 2
    out, _ = run(False)
    assert out.overflowed and out.n_isect == m
    assert policy.capacity >= m                  # the count read back resized the grid's buffers
    policy.capacity = 2
    out, got = run(True)
    assert not out.overflowed and out.binned.pairs.capacity >= m
    for k in want:
        assert np.array_equal(got[k], want[k]), k
