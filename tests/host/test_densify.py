"""Adaptive density control (train/densify.py): clone, 4D split, prune."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from endowave_cl.gaussians import Gaussians, covariance_4d
from endowave_cl.train.config import DENSIFY_GRAD_THRESHOLD, TrainConfig
from endowave_cl.train.densify import densify_and_prune, logit, moment_source_index, sigmoid
from endowave_cl.train.motion import motion_of

CFG = TrainConfig(densify_grad_threshold=DENSIFY_GRAD_THRESHOLD)   # as resolve_density makes it up to 320x256
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
    out, src = densify_and_prune(g, grad, count, radius, CFG, EXTENT, prune_big=True,
                                 stats=stats)
    np.testing.assert_array_equal(src, [0, 1, 4, 1, 2, 2])
    assert (stats["cloned"], stats["split"], stats["pruned"]) == (1, 1, 2)
    np.testing.assert_array_equal(stats["is_new"], [False, False, False, True, True, True])
    np.testing.assert_array_equal(moment_source_index(src, stats["is_new"]), [0, 1, 4, -1, -1, -1])
    # survivors and the clone are exact copies but for the opacity the clone pair shares
    for i, s in enumerate(src[:4]):
        for name, a in out.as_dict().items():
            if name == "opacity" and s == 1:
                np.testing.assert_allclose(sigmoid(a[i]), 1 - np.sqrt(0.5), rtol=1e-5)
                continue
            np.testing.assert_array_equal(a[i], getattr(g, name)[s], err_msg=name)
    # children: one spatial axis of the (isotropic) parent / 1.6, velocity and temporal std kept,
    # appearance copied, new centres (the split rule in detail: the next test)
    cond_p, st_p, v_p = motion_of(covariance_4d(g)[2:3])
    cond_c, st_c, v_c = motion_of(covariance_4d(out)[4:6])
    for i in range(2):
        np.testing.assert_allclose(np.linalg.eigvalsh(cond_c[i]), 0.05 ** 2 * np.array([1 / 1.6 ** 2, 1, 1]),
                                   rtol=1e-4)
        np.testing.assert_allclose(st_c[i], st_p[0], rtol=1e-4)
        np.testing.assert_allclose(v_c[i], v_p[0], rtol=1e-4, atol=1e-6)
    for i in (4, 5):
        np.testing.assert_array_equal(out.sh[i], g.sh[2])
        assert np.any(out.means[i, :3] != g.means[2, :3]) and out.means[i, 3] == g.means[2, 3]
    assert not np.array_equal(out.means[4], out.means[5])
    # without big-Gaussian pruning row 5 survives
    out2, src2 = densify_and_prune(g, grad, count, radius, CFG, EXTENT)  # default off
    np.testing.assert_array_equal(src2, [0, 1, 4, 5, 1, 2, 2])


def test_world_size_prune_and_empty_scene():
    g = _scene(3)
    g.scales[1, 0] = math.log(0.5)  # > prune_world_size * extent
    z = np.zeros(3)
    out, src = densify_and_prune(g, z, z, z, CFG, EXTENT, prune_big=True)
    np.testing.assert_array_equal(src, [0, 2])
    out, src = densify_and_prune(g, z, z, z, CFG, 10.0, prune_big=True)  # extent 10
    np.testing.assert_array_equal(src, [0, 1, 2])
    e = Gaussians.empty()
    out, src = densify_and_prune(e, np.zeros(0), np.zeros(0), np.zeros(0), CFG, EXTENT)
    assert len(out) == 0 and src.shape == (0,)


def test_max_gaussians_budget_takes_largest_gradients():
    g = _scene(5)
    grad = np.array([1, 5, 3, 4, 2]) * CFG.densify_grad_threshold
    cfg = replace(CFG, max_gaussians=7)  # room for 2 clones
    out, src = densify_and_prune(g, grad, np.ones(5), np.zeros(5), cfg, EXTENT)
    np.testing.assert_array_equal(src, [0, 1, 2, 3, 4, 1, 3])
    cfg = replace(CFG, max_gaussians=5)  # full: nothing added
    out, src = densify_and_prune(g, grad, np.ones(5), np.zeros(5), cfg, EXTENT)
    np.testing.assert_array_equal(src, np.arange(5))


def test_cap_turnover_replaces_the_least_opaque_non_candidates():
    """At the cap, cap_turnover x cap of the least opaque non-candidates make room for the candidates
    that did not fit, largest gradient first, as many as they need; 0 leaves the cap as it was."""
    g = _scene(8)
    g.opacity[:] = [logit(p) for p in (0.9, 0.2, 0.05, 0.6, 0.3, 0.01, 0.8, 0.5)]
    thr = CFG.densify_grad_threshold
    grad = np.array([5, 0, 0, 4, 0, 0, 3, 0]) * thr      # candidates 0, 3, 6 (clones: one row each)
    full = replace(CFG, max_gaussians=8)
    stats = {}
    out, src = densify_and_prune(g, grad, np.ones(8), np.zeros(8), replace(full, cap_turnover=0.25), EXTENT,
                                 stats=stats)
    # room for 2 (0.25 x 8): rows 5 (0.01) and 2 (0.05) go; candidates 0 and 3 are cloned, 6 is not
    np.testing.assert_array_equal(src, [0, 1, 3, 4, 6, 7, 0, 3])
    assert (stats["cloned"], stats["replaced"], len(out)) == (2, 2, 8)
    # more room than the candidates need: only as many rows as they take
    out, src = densify_and_prune(g, grad, np.ones(8), np.zeros(8), replace(full, cap_turnover=1.0), EXTENT,
                                 stats=stats)
    assert stats["replaced"] == 3 and len(out) == 8 and sorted(src[-3:]) == [0, 3, 6]
    assert 5 not in src and 2 not in src and 1 not in src and 4 in src      # 0.01, 0.05, 0.2 go; 0.3 stays
    # under the cap the free rows are used first, then the turnover
    out, src = densify_and_prune(g, grad, np.ones(8), np.zeros(8),
                                 replace(CFG, max_gaussians=9, cap_turnover=0.25), EXTENT, stats=stats)
    assert stats["replaced"] == 2 and len(out) == 9
    # turnover 0: the cap as before, nothing replaced
    out, src = densify_and_prune(g, grad, np.ones(8), np.zeros(8), replace(full, cap_turnover=0.0), EXTENT,
                                 stats=stats)
    np.testing.assert_array_equal(src, np.arange(8))
    assert stats["replaced"] == 0


def test_split_children_keep_the_parents_moments_and_motion():
    """Two children of a rotated, moving parent: centres +-a sigma along the major axis of the
    parent's conditional spatial covariance, that axis's std / 1.6, the other axes, velocity,
    lifetime and time centre unchanged, so that the equal mixture of the children has the parent's
    mean and conditional covariance at every time."""
    g = _scene(1, scale=LARGE)
    g.scales[:] = np.log([0.05, 0.02, 0.08, 0.3])
    rng = np.random.default_rng(1)
    g.quat_l[:], g.quat_r[:] = rng.standard_normal(4), rng.standard_normal(4)
    g.means[:] = [0.1, -0.2, 3.0, 0.4]
    cond_p, st_p, v_p = motion_of(covariance_4d(g))
    assert np.abs(v_p).max() > 1e-3                       # the parent moves
    cfg = replace(CFG, prune_opacity=0.0)
    out, src = densify_and_prune(g, np.ones(1), np.ones(1), np.zeros(1), cfg, EXTENT)
    assert len(out) == 2 and np.all(src == 0)
    cond_c, st_c, v_c = motion_of(covariance_4d(out))
    np.testing.assert_allclose(st_c, st_p[0], rtol=1e-4)
    np.testing.assert_allclose(v_c, np.repeat(v_p, 2, 0), rtol=1e-4, atol=1e-7)
    np.testing.assert_allclose(out.means[:, 3], g.means[0, 3])
    x = out.means[:, :3].astype(np.float64)
    np.testing.assert_allclose(x.mean(0), g.means[0, :3], atol=1e-6)
    lam, U = np.linalg.eigh(cond_p[0])
    off = x - g.means[0, :3]
    np.testing.assert_allclose(np.abs(off @ U[:, 2]), np.sqrt(1 - 1 / 1.6 ** 2) * np.sqrt(lam[2]), rtol=1e-4)
    mixture = cond_c.mean(0) + np.cov(x.T, bias=True)      # law of total variance
    np.testing.assert_allclose(mixture, cond_p[0], rtol=1e-4, atol=1e-9)
    np.testing.assert_allclose(np.linalg.eigvalsh(cond_c[0]), np.sort([lam[0], lam[1], lam[2] / 1.6 ** 2]),
                               rtol=1e-4)


def test_densified_copies_share_the_opacity():
    """A clone and its original, and the children of a split, composite to the parent's opacity."""
    g = _scene(2)
    g.scales[1, :3] = LARGE
    g.opacity[:] = logit(0.6)
    out, src = densify_and_prune(g, np.ones(2), np.ones(2), np.zeros(2), CFG, EXTENT)
    np.testing.assert_array_equal(src, [0, 0, 1, 1])      # original 0, its clone, two children of 1
    o = sigmoid(out.opacity)
    np.testing.assert_allclose(1 - (1 - o[0]) * (1 - o[1]), 0.6, rtol=1e-5)   # original + clone
    np.testing.assert_allclose(1 - (1 - o[2]) * (1 - o[3]), 0.6, rtol=1e-5)   # two children


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
    new_g, src = densify_and_prune(g, grad, np.ones(4), np.zeros(4), CFG, EXTENT,
                                   stats=stats)
    np.testing.assert_array_equal(src, [0, 1, 2, 1, 3, 3])
    opt.remap(upload(rt, new_g), moment_source_index(src, stats["is_new"]))
    st = opt.state_dict()
    np.testing.assert_array_equal(st["exp_avg"]["opacity"][:3], old["exp_avg"]["opacity"][:3])
    assert np.all(st["exp_avg"]["opacity"][3:] == 0) and np.all(st["exp_avg_sq"]["sh"][3:] == 0)


def test_temporal_row_order_keeps_the_rows_alive_at_one_time_together():
    from endowave_cl.reference.select import live_flags_ref
    from endowave_cl.train.densify import temporal_row_order
    g = Gaussians.random(3000, seed=4)
    rng = np.random.default_rng(4)
    g.means[:, 3] = rng.uniform(-0.2, 1.2, len(g))   # time centres inside and past the sequence
    g.scales[:, 3] = rng.uniform(-6.0, 0.0, len(g))   # lifetimes from a few frames to all of it
    g.scales[7, 0] = 1e30                             # bad rows (overflow, NaN) still get a place
    g.means[9, 3] = np.nan
    twin = g.take(np.r_[np.arange(len(g)), 5])        # row 3000: an exact copy of row 5
    order = temporal_row_order(twin)
    assert np.array_equal(np.sort(order), np.arange(len(twin)))      # a permutation
    assert np.flatnonzero(order == 5)[0] < np.flatnonzero(order == 3000)[0]   # ties keep their order
    assert len(temporal_row_order(g.take(np.zeros(0, int)))) == 0

    def runs(rows):   # runs of consecutive rows
        return 1 + int(np.count_nonzero(np.diff(np.sort(rows)) != 1)) if len(rows) else 0
    inv = np.empty_like(order)
    inv[order] = np.arange(len(order))
    before = after = 0
    for t in np.linspace(0.0, 1.0, 9):
        with np.errstate(over="ignore", invalid="ignore"):   # the overflowing row
            live = np.flatnonzero(live_flags_ref(twin, t, 1.0))
        assert 0 < len(live) < len(twin)
        before += runs(live)
        after += runs(inv[live])
    assert after < 0.25 * before, (before, after)
