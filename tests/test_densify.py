"""Adaptive density control (train/densify.py): clone, 4D split, prune, opacity reset."""
from __future__ import annotations

import math

import numpy as np
import pytest

from endowave_cl.gaussians import Gaussians
from endowave_cl.train.config import TrainConfig
from endowave_cl.train.densify import (covariance_4d, densify_and_prune, logit, moment_source_index,
                                       reset_opacity, sigmoid)
from endowave_cl.train.motion import motion_of

CFG = TrainConfig()
EXTENT = 1.0
SMALL = math.log(0.005)   # below percent_dense * extent = 0.01: clone
LARGE = math.log(0.05)    # above it: split (and below prune_world_size * extent = 0.1)


def _scene(n, scale=SMALL, seed=0):
    g = Gaussians.random(n, seed=seed)
    g.scales[:] = scale
    g.scales[:, 3] = math.log(0.2)
    g.opacity[:] = logit(0.5)
    g.quat_l[:] = g.quat_r[:] = [1, 0, 0, 0]   # still: the spatial scales are the spatial size
    return g


def test_clone_split_prune_hand_built():
    g = _scene(6)
    g.scales[2, :3] = LARGE                       # 2: large -> split
    g.opacity[3] = logit(0.001)                   # 3: transparent -> pruned
    hi = 10 * CFG.densify_grad_threshold
    grad = np.array([0.05, 3, 3, 0, 5, 0]) * hi   # 0: half the threshold: not a candidate
    count = np.array([1, 3, 3, 1, 0, 1])          # 4: never seen: mean gradient 0
    radius = np.array([1, 2, 3, 4, 5, 500])       # 5: too big on screen
    stats = {}
    out, src = densify_and_prune(g, grad, count, radius, CFG, EXTENT, np.random.default_rng(0), prune_big=True,
                                 stats=stats)
    np.testing.assert_array_equal(src, [0, 1, 4, 1, 2, 2])
    assert (stats["cloned"], stats["split"], stats["pruned"]) == (1, 1, 2)
    np.testing.assert_array_equal(stats["is_new"], [False, False, False, True, True, True])
    np.testing.assert_array_equal(moment_source_index(src, stats["is_new"]), [0, 1, 4, -1, -1, -1])
    # survivors and the clone are exact copies
    for i, s in enumerate(src[:4]):
        for name, a in out.as_dict().items():
            np.testing.assert_array_equal(a[i], getattr(g, name)[s], err_msg=name)
    # children: conditional spatial covariance / 1.6^2, velocity and temporal std kept, appearance
    # copied, new 4D centres
    cond_p, st_p, v_p = motion_of(covariance_4d(g)[2:3])
    cond_c, st_c, v_c = motion_of(covariance_4d(out)[4:6])
    for i in range(2):
        np.testing.assert_allclose(cond_c[i], cond_p[0] / 1.6 ** 2, rtol=1e-4, atol=1e-9)
        np.testing.assert_allclose(st_c[i], st_p[0], rtol=1e-4)
        np.testing.assert_allclose(v_c[i], v_p[0], rtol=1e-4, atol=1e-6)
    for i in (4, 5):
        np.testing.assert_array_equal(out.sh[i], g.sh[2])
        assert np.all(out.means[i] != g.means[2])
    assert not np.array_equal(out.means[4], out.means[5])
    # without big-Gaussian pruning row 5 survives
    out2, src2 = densify_and_prune(g, grad, count, radius, CFG, EXTENT, np.random.default_rng(0))  # default off
    np.testing.assert_array_equal(src2, [0, 1, 4, 5, 1, 2, 2])


def test_world_size_prune_and_empty_scene():
    g = _scene(3)
    g.scales[1, 0] = math.log(0.5)  # > prune_world_size * extent
    z = np.zeros(3)
    out, src = densify_and_prune(g, z, z, z, CFG, EXTENT, np.random.default_rng(0), prune_big=True)
    np.testing.assert_array_equal(src, [0, 2])
    out, src = densify_and_prune(g, z, z, z, CFG, 10.0, np.random.default_rng(0), prune_big=True)  # extent 10
    np.testing.assert_array_equal(src, [0, 1, 2])
    e = Gaussians.empty()
    out, src = densify_and_prune(e, np.zeros(0), np.zeros(0), np.zeros(0), CFG, EXTENT, np.random.default_rng(0))
    assert len(out) == 0 and src.shape == (0,)


def test_max_gaussians_budget_takes_largest_gradients():
    g = _scene(5)
    grad = np.array([1, 5, 3, 4, 2]) * CFG.densify_grad_threshold
    cfg = TrainConfig(max_gaussians=7)  # room for 2 clones
    out, src = densify_and_prune(g, grad, np.ones(5), np.zeros(5), cfg, EXTENT, np.random.default_rng(0))
    np.testing.assert_array_equal(src, [0, 1, 2, 3, 4, 1, 3])
    cfg = TrainConfig(max_gaussians=5)  # full: nothing added
    out, src = densify_and_prune(g, grad, np.ones(5), np.zeros(5), cfg, EXTENT, np.random.default_rng(0))
    np.testing.assert_array_equal(src, np.arange(5))


def test_split_children_sample_the_parent_4d_gaussian():
    """Children of identical parents are i.i.d. draws of N(mu, Sigma) (4D, rotated, with time).

    With n draws the sample mean of coordinate i has standard error sqrt(Sigma_ii / n) and the
    sample covariance entry (i, j) has standard error sqrt((Sigma_ii Sigma_jj + Sigma_ij^2) / n)
    (Gaussian fourth moments).  We allow 5 standard errors: a correct sampler fails one of the
    4 + 10 checks with probability below 1e-5, and the seed is fixed, so the test is stable;
    a sampler that ignored the rotation, the time axis or the scales would miss by far more.
    """
    P = 5000
    g = _scene(P, scale=LARGE)
    g.scales[:] = np.log([0.05, 0.02, 0.08, 0.3])
    rng = np.random.default_rng(1)
    ql, qr = rng.standard_normal(4), rng.standard_normal(4)
    g.quat_l[:] = ql
    g.quat_r[:] = qr
    g.means[:] = [0.1, -0.2, 3.0, 0.4]
    sigma = covariance_4d(Gaussians(**{k: v[:1] for k, v in g.as_dict().items()}))[0]
    assert abs(sigma[0, 3]) > 1e-4  # the rotation couples space and time
    cfg = TrainConfig(max_gaussians=10 ** 6, prune_opacity=0.0)
    out, src = densify_and_prune(g, np.ones(P), np.ones(P), np.zeros(P), cfg, EXTENT, np.random.default_rng(2),
                                 prune_big=False)
    assert len(out) == 2 * P and np.all(src == np.repeat(np.arange(P), 2))
    x = out.means.astype(np.float64)
    n = len(x)
    d = np.sqrt(np.diag(sigma))
    assert np.all(np.abs(x.mean(0) - g.means[0]) < 5 * d / np.sqrt(n))
    cov = np.cov(x.T, bias=True)
    se = np.sqrt((np.outer(d * d, d * d) + sigma ** 2) / n)
    assert np.all(np.abs(cov - sigma) < 5 * se), (cov, sigma)


def test_reset_opacity_caps_at_value():
    g = _scene(3)
    g.opacity[:] = [logit(0.5), logit(0.001), logit(0.01)]
    r = reset_opacity(g, 0.01)
    np.testing.assert_allclose(sigmoid(r.opacity), [0.01, 0.001, 0.01], rtol=1e-5)
    np.testing.assert_array_equal(r.means, g.means)
    assert sigmoid(g.opacity[0]) == pytest.approx(0.5)  # the input is not modified


def test_densify_then_adam_remap_zeroes_new_rows(rt):
    from endowave_cl.gaussians import upload
    from endowave_cl.ops.adam import DeviceAdam
    g = _scene(4)
    g.scales[3, :3] = LARGE
    lrs = {"means": 1e-3, "scales": 1e-3, "quat_l": 1e-3, "quat_r": 1e-3, "opacity": 1e-2, "sh": 1e-3,
           "phase": 1e-3}
    opt = DeviceAdam(rt, upload(rt, g), lrs)
    import pyopencl.array as cla
    opt.step({n: cla.to_device(rt.queue, np.ones_like(a)) for n, a in g.as_dict().items()})
    old = opt.state_dict()
    grad = np.array([0, 1, 0, 1]) * CFG.densify_grad_threshold
    stats = {}
    new_g, src = densify_and_prune(g, grad, np.ones(4), np.zeros(4), CFG, EXTENT, np.random.default_rng(0),
                                   stats=stats)
    np.testing.assert_array_equal(src, [0, 1, 2, 1, 3, 3])
    opt.remap(upload(rt, new_g), moment_source_index(src, stats["is_new"]))
    st = opt.state_dict()
    np.testing.assert_array_equal(st["exp_avg"]["opacity"][:3], old["exp_avg"]["opacity"][:3])
    assert np.all(st["exp_avg"]["opacity"][3:] == 0) and np.all(st["exp_avg_sq"]["sh"][3:] == 0)
