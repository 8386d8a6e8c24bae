"""Device Adam (cl/adam.cl, ops/adam.py) against the numpy reference and torch.optim.Adam."""
from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import small
from endowave_cl.errors import EndowaveError
from endowave_cl.gaussians import PARAM_NAMES, Gaussians, upload
from endowave_cl.ops.adam import (ADAM_EPS, DeviceAdam, anneal_factor, element_lrs, group_lr_layout, position_lr)
from endowave_cl.reference.adam import adam_step_ref

LRS = {"means": 1.6e-4, "means_t": 1e-3, "scales": 5e-3, "quat_l": 1e-3, "quat_r": 2e-3,
       "opacity": 0.05, "sh": 2.5e-3, "phase": 4e-3}


def _grads(g: Gaussians, rng) -> dict:
    return {n: rng.standard_normal(a.shape).astype(np.float32) * rng.uniform(0.01, 2.0)
            for n, a in g.as_dict().items()}


def _run_both(rt, g, steps, lr_sched, seed=0):
    """Run the device Adam and the reference side by side; returns (device params, ref params)."""
    rng = np.random.default_rng(seed)
    params = upload(rt, g)
    opt = DeviceAdam(rt, params, lr_sched(0))
    ref = {n: a.copy() for n, a in g.as_dict().items()}
    m = {n: np.zeros_like(a) for n, a in ref.items()}
    v = {n: np.zeros_like(a) for n, a in ref.items()}
    for s in range(steps):
        lrs = lr_sched(s)
        grads = _grads(g, rng)
        opt.step({n: _to_dev(rt, a) for n, a in grads.items()}, lrs)
        for n in PARAM_NAMES:
            lr = element_lrs(n, ref[n].shape, opt.lrs)
            ref[n], m[n], v[n] = adam_step_ref(ref[n], grads[n], m[n], v[n], lr, s + 1)
    out = {n: params[n].get() for n in PARAM_NAMES}
    st = opt.state_dict()
    for n in PARAM_NAMES:
        np.testing.assert_allclose(st["exp_avg"][n], m[n], rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(st["exp_avg_sq"][n], v[n], rtol=1e-5, atol=1e-9)
    return out, ref


def _to_dev(rt, a):
    import pyopencl.array as cla
    return cla.to_device(rt.queue, np.ascontiguousarray(a, np.float32))


def test_adam_matches_reference_over_steps_with_changing_lrs(rt):
    g = Gaussians.random(small(37, 3), seed=1)

    def sched(s):
        d = dict(LRS)
        d["means"] = position_lr(s, 5, extent=2.0)
        d["scales"] = 0.0  # frozen group
        return d

    dev, ref = _run_both(rt, g, steps=small(5, 2), lr_sched=sched)
    for n in PARAM_NAMES:
        np.testing.assert_allclose(dev[n], ref[n], rtol=1e-5, atol=2e-6, err_msg=n)
    np.testing.assert_array_equal(dev["scales"], g.scales)  # lr 0: untouched
    assert not np.array_equal(dev["opacity"], g.opacity)


def test_adam_frozen_lanes_inside_a_run(rt):
    """sh_rest = 0, means_t = 0 and scales_t = 0 freeze some columns of a row: within a kernel's
    8-element run the frozen lanes keep their values while the others step."""
    g = Gaussians.random(small(23, 3), seed=5)

    def sched(s):
        return dict(LRS, sh_rest=0.0, means_t=0.0, scales_t=0.0)

    dev, ref = _run_both(rt, g, steps=small(3, 2), lr_sched=sched)
    for n in PARAM_NAMES:
        np.testing.assert_allclose(dev[n], ref[n], rtol=1e-5, atol=2e-6, err_msg=n)
    sh0, sh = g.sh.reshape(len(g.sh), -1), dev["sh"].reshape(len(g.sh), -1)
    np.testing.assert_array_equal(sh[:, 3:], sh0[:, 3:])   # frozen: every coefficient but n = 0 DC
    np.testing.assert_array_equal(dev["scales"][:, 3], g.scales[:, 3])
    assert not np.array_equal(dev["scales"][:, :3], g.scales[:, :3])
    assert not np.array_equal(sh[:, :3], sh0[:, :3])
    np.testing.assert_array_equal(dev["means"][:, 3], g.means[:, 3])
    assert not np.array_equal(dev["means"][:, :3], g.means[:, :3])


def _run_visible(rt, g, steps, seed=0):
    """Device Adam with a random visibility per step (visible = radius, 0 culled) against the
    reference with the culled rows' learning rates set to 0."""
    rng = np.random.default_rng(seed)
    params = upload(rt, g)
    opt = DeviceAdam(rt, params, LRS)
    ref = {n: a.copy() for n, a in g.as_dict().items()}
    m = {n: np.zeros_like(a) for n, a in ref.items()}
    v = {n: np.zeros_like(a) for n, a in ref.items()}
    never = np.zeros(len(g), bool)
    never[::5] = True                        # culled at every step
    for s in range(steps):
        radius = np.where(never | (rng.random(len(g)) < 0.5), 0, rng.integers(1, 40, len(g))).astype(np.int32)
        grads = _grads(g, rng)
        for n in PARAM_NAMES:                # a culled Gaussian's gradient is 0
            grads[n][radius == 0] = 0.0
        opt.step({n: _to_dev(rt, a) for n, a in grads.items()}, visible=_to_dev_i(rt, radius))
        for n in PARAM_NAMES:
            lr = element_lrs(n, ref[n].shape, opt.lrs)
            lr[radius == 0] = 0.0
            ref[n], m[n], v[n] = adam_step_ref(ref[n], grads[n], m[n], v[n], lr, s + 1)
    st = opt.state_dict()
    return {n: params[n].get() for n in PARAM_NAMES}, st, ref, m, v, never


def _to_dev_i(rt, a):
    import pyopencl.array as cla
    return cla.to_device(rt.queue, np.ascontiguousarray(a, np.int32))


def test_adam_skip_culled_matches_reference(rt):
    """visible=radius: the rows of culled Gaussians keep parameters and moments (every group,
    runs of 8 that straddle Gaussians included); the others step as the reference does."""
    g = Gaussians.random(small(37, 7), seed=3)
    dev, st, ref, m, v, never = _run_visible(rt, g, small(4, 2))
    for n in PARAM_NAMES:
        np.testing.assert_allclose(dev[n], ref[n], rtol=1e-5, atol=2e-6, err_msg=n)
        np.testing.assert_allclose(st["exp_avg"][n], m[n], rtol=1e-5, atol=1e-7, err_msg=n)
        np.testing.assert_allclose(st["exp_avg_sq"][n], v[n], rtol=1e-5, atol=1e-9, err_msg=n)
        np.testing.assert_array_equal(dev[n][never], getattr(g, n)[never].astype(np.float32), err_msg=n)
        assert not st["exp_avg"][n][never].any() and st["exp_avg"][n][~never].any(), n


def test_adam_visible_must_match_rows(rt):
    g = Gaussians.random(5, seed=1)
    opt = DeviceAdam(rt, upload(rt, g), LRS)
    grads = {n: _to_dev(rt, a) for n, a in _grads(g, np.random.default_rng(0)).items()}
    with pytest.raises(EndowaveError, match="visible must be int32"):
        opt.step(grads, visible=_to_dev_i(rt, np.ones(4, np.int32)))
    assert opt.step_count == 0


@pytest.mark.oclgrind
def test_adam_skip_culled_tiny_oclgrind(rt):
    g = Gaussians.random(3, seed=2, degree=1, nt=1)
    dev, st, ref, m, v, never = _run_visible(rt, g, 2)
    for n in PARAM_NAMES:
        np.testing.assert_allclose(dev[n], ref[n], rtol=1e-5, atol=2e-6, err_msg=n)


@pytest.mark.oclgrind
def test_adam_tiny_oclgrind(rt):
    g = Gaussians.random(2, seed=2, degree=1, nt=1)
    dev, ref = _run_both(rt, g, steps=2, lr_sched=lambda s: LRS)
    for n in PARAM_NAMES:
        np.testing.assert_allclose(dev[n], ref[n], rtol=1e-5, atol=2e-6, err_msg=n)


def test_adam_matches_torch(rt):
    torch = pytest.importorskip("torch")
    g = Gaussians.random(small(29, 2), seed=3)
    lrs = {n: LRS[n] for n in PARAM_NAMES}
    lrs["sh_rest"] = lrs["sh"]  # torch groups are whole tensors: one lr per group here
    lrs["means_t"] = 7e-4
    params = upload(rt, g)
    opt = DeviceAdam(rt, params, lrs)
    tp = {n: torch.tensor(a, requires_grad=True) for n, a in g.as_dict().items() if n != "means"}
    txyz = torch.tensor(g.means[:, :3], requires_grad=True)
    tt = torch.tensor(g.means[:, 3:], requires_grad=True)
    groups = [{"params": [tp[n]], "lr": lrs[n]} for n in tp]
    groups += [{"params": [txyz], "lr": lrs["means"]}, {"params": [tt], "lr": lrs["means_t"]}]
    topt = torch.optim.Adam(groups, betas=(0.9, 0.999), eps=ADAM_EPS)
    rng = np.random.default_rng(4)
    for _ in range(4):
        grads = _grads(g, rng)
        opt.step({n: _to_dev(rt, a) for n, a in grads.items()})
        for n in tp:
            tp[n].grad = torch.tensor(grads[n])
        txyz.grad = torch.tensor(grads["means"][:, :3])
        tt.grad = torch.tensor(grads["means"][:, 3:])
        topt.step()
    for n in tp:
        np.testing.assert_allclose(params[n].get(), tp[n].detach().numpy(), rtol=1e-5, atol=2e-6, err_msg=n)
    means = params["means"].get()
    np.testing.assert_allclose(means[:, :3], txyz.detach().numpy(), rtol=1e-5, atol=2e-6)
    np.testing.assert_allclose(means[:, 3:], tt.detach().numpy(), rtol=1e-5, atol=2e-6)


def test_lr_layout_means_time_and_sh_dc():
    lr = element_lrs("means", (5, 4), LRS)
    assert np.all(lr[:, :3] == np.float32(LRS["means"])) and np.all(lr[:, 3] == np.float32(LRS["means_t"]))
    sh_shape = (4, 3, 16, 3)
    lr = element_lrs("sh", sh_shape, LRS)
    assert np.all(lr[:, 0, 0, :] == np.float32(LRS["sh"]))
    rest = np.ones(sh_shape, bool)
    rest[:, 0, 0, :] = False
    assert np.all(lr[rest] == np.float32(LRS["sh"] / 20))
    lr = element_lrs("scales", (5, 4), dict(LRS, scales_t=2e-2))
    assert np.all(lr[:, :3] == np.float32(LRS["scales"])) and np.all(lr[:, 3] == np.float32(2e-2))
    # defaults: means_t falls back to the means lr, scales_t to the scales lr
    assert group_lr_layout("means", (2, 4), {"means": 0.5})[3] == 0.5
    assert group_lr_layout("scales", (2, 4), {"scales": 0.25})[1:] == (3, 0.25, 0.25)
    with pytest.raises(EndowaveError, match="opacity"):
        group_lr_layout("opacity", (3,), {"means": 1.0})


def test_empty_scene_and_shape_errors(rt):
    g = Gaussians.empty()
    params = upload(rt, g)
    opt = DeviceAdam(rt, params, LRS)
    opt.step({n: _to_dev(rt, a) for n, a in g.as_dict().items()})
    st = opt.state_dict()
    assert st["step"] == 1 and st["exp_avg"]["sh"].shape == (0, 3, 16, 3)
    g2 = Gaussians.random(3)
    opt2 = DeviceAdam(rt, upload(rt, g2), LRS)
    bad = {n: _to_dev(rt, a) for n, a in g2.as_dict().items()}
    bad["opacity"] = _to_dev(rt, np.zeros(4, np.float32))
    with pytest.raises(EndowaveError, match="opacity"):
        opt2.step(bad)


def test_state_dict_round_trip_and_remap(rt):
    g = Gaussians.random(6, seed=5)
    params = upload(rt, g)
    opt = DeviceAdam(rt, params, LRS)
    rng = np.random.default_rng(6)
    for _ in range(2):
        opt.step({n: _to_dev(rt, a) for n, a in _grads(g, rng).items()})
    st = opt.state_dict()
    opt2 = DeviceAdam(rt, upload(rt, g), LRS)
    opt2.load_state_dict(st)
    st2 = opt2.state_dict()
    assert st2["step"] == 2
    for n in PARAM_NAMES:
        np.testing.assert_array_equal(st2["exp_avg_sq"][n], st["exp_avg_sq"][n])
    # remap: rows 4, 0 kept, a new row, a copy of row 0
    src = np.array([4, 0, -1, 0])
    g_new = Gaussians(**{n: a[np.maximum(src, 0)] for n, a in g.as_dict().items()})
    opt.remap(upload(rt, g_new), src)
    st3 = opt.state_dict()
    for n in PARAM_NAMES:
        for key in ("exp_avg", "exp_avg_sq"):
            np.testing.assert_array_equal(st3[key][n][[0, 1, 3]], st[key][n][[4, 0, 0]])
            assert np.all(st3[key][n][2] == 0)
    assert st3["step"] == 2
    with pytest.raises(EndowaveError, match="source_index"):
        opt.remap(upload(rt, g_new), np.array([0, 1]))
    with pytest.raises(EndowaveError, match="shape"):
        bad = dict(st)
        bad["exp_avg"] = dict(st["exp_avg"], opacity=np.zeros(2, np.float32))
        opt2.load_state_dict(bad)


def test_anneal_factor():
    assert anneal_factor(0, 10, 20, 0.01) == 1.0 and anneal_factor(10, 10, 20, 0.01) == 1.0
    assert math.isclose(anneal_factor(15, 10, 20, 0.01), 0.1, rel_tol=1e-12)   # geometric midpoint
    assert math.isclose(anneal_factor(20, 10, 20, 0.01), 0.01, rel_tol=1e-12)
    assert math.isclose(anneal_factor(99, 10, 20, 0.01), 0.01, rel_tol=1e-12)  # held after the end
    assert anneal_factor(11, 10, 10, 0.5) == 0.5                                # empty window: at the end
    assert anneal_factor(15, 10, 20, 1.0) == 1.0


def test_position_lr_schedule():
    assert math.isclose(position_lr(0, 100), 1.6e-4, rel_tol=1e-9)
    assert math.isclose(position_lr(100, 100), 1.6e-6, rel_tol=1e-9)
    assert math.isclose(position_lr(500, 100), 1.6e-6, rel_tol=1e-9)  # clamped after the end
    assert math.isclose(position_lr(50, 100), 1.6e-5, rel_tol=1e-9)   # geometric midpoint
    assert math.isclose(position_lr(50, 100, extent=3.0), 4.8e-5, rel_tol=1e-9)
    assert position_lr(10, 100) > position_lr(11, 100)


@pytest.mark.oclgrind
def test_adam_frozen_group_without_gradient_and_empty_scene_oclgrind(rt):
    """lr 0 with no gradient (placeholder buffer) next to live groups; then N = 0."""
    g = Gaussians.random(2, seed=7, degree=1, nt=1)
    params = upload(rt, g)
    lrs = dict(LRS, phase=0.0)
    opt = DeviceAdam(rt, params, lrs)
    grads = _grads(g, np.random.default_rng(8))
    dev = {n: _to_dev(rt, a) for n, a in grads.items()}
    dev["phase"] = None
    opt.step(dev)
    np.testing.assert_array_equal(params["phase"].get(), g.phase)
    lr = element_lrs("opacity", g.opacity.shape, lrs)
    want, _, _ = adam_step_ref(g.opacity, grads["opacity"], np.zeros(2, np.float32), np.zeros(2, np.float32), lr, 1)
    np.testing.assert_allclose(params["opacity"].get(), want, rtol=1e-5, atol=2e-6)
    with pytest.raises(EndowaveError, match="no gradient for parameter group 'means'"):
        opt.step(dict(dev, means=None))
    assert opt.state_dict()["step"] == 1  # a refused step is not counted
    e = Gaussians.empty(degree=1, nt=1)
    opt0 = DeviceAdam(rt, upload(rt, e), LRS)
    opt0.step({n: _to_dev(rt, a) for n, a in e.as_dict().items()})
    assert opt0.state_dict()["step"] == 1


@pytest.mark.oclgrind
@pytest.mark.parametrize("n", [small(1000, 70), 1, 0])
def test_opacity_reset_matches_reference(rt, n):
    """cl/opacity_reset.cl caps the opacity logits in place at logit(0.01), as opacity_reset_ref."""
    import pyopencl.array as cla
    from endowave_cl.ops.adam import opacity_reset
    from endowave_cl.reference.adam import opacity_reset_ref
    cap = math.log(0.01 / 0.99)
    x = np.random.default_rng(n).uniform(-8, 8, n).astype(np.float32)
    if n > 3:
        x[:3] = [np.float32(cap), np.nan, -np.inf]     # at the cap, NaN (stays NaN), -inf (kept)
    dev = cla.to_device(rt.queue, x)
    opacity_reset(rt, dev, cap)
    want = opacity_reset_ref(x, cap)
    np.testing.assert_array_equal(dev.get(), want)
    assert (want[~np.isnan(x)] <= np.float32(cap)).all()         # every value but the NaN capped
    if n > 3:
        assert np.isnan(want[1]) and want[2] == -np.inf
        assert (x[3:] > cap).any() and (want[3:] <= np.float32(cap)).all()
        np.testing.assert_array_equal(want[3:][x[3:] <= cap], x[3:][x[3:] <= cap])   # below: untouched


@pytest.mark.oclgrind
@pytest.mark.parametrize("compact", [False, True])
def test_adam_gated_step_changes_nothing(rt, compact):
    """skip set (the step gate): neither parameters nor moments move, on adam_step and on
    adam_step_rows; skip 0: the same bits as a step without the gate."""
    g = Gaussians.random(small(19, 5), seed=4, degree=1, nt=1)
    rng = np.random.default_rng(5)
    grads = _grads(g, rng)
    rows = np.array([0, 3, 4, 9, 17, -1][: 6 if len(g) > 17 else 3], np.int32)
    if compact:
        rows = rows[rows < len(g)]
        grads = {n: a[np.maximum(rows, 0)] for n, a in grads.items()}
    results = []
    for skip in (None, 0, 1):
        params = upload(rt, g)
        opt = DeviceAdam(rt, params, LRS)
        opt.step({n: _to_dev(rt, a) for n, a in grads.items()}, rows=_to_dev_i(rt, rows) if compact else None)
        opt.step({n: _to_dev(rt, a) for n, a in grads.items()}, rows=_to_dev_i(rt, rows) if compact else None,
                 skip=None if skip is None else _to_dev_i(rt, np.array([skip])))
        st = opt.state_dict()
        results.append(({n: params[n].get() for n in PARAM_NAMES}, st))
    (p_none, s_none), (p_zero, s_zero), (p_one, s_one) = results
    once = DeviceAdam(rt, upload(rt, g), LRS)
    p_once = once.params
    once.step({n: _to_dev(rt, a) for n, a in grads.items()}, rows=_to_dev_i(rt, rows) if compact else None)
    for n in PARAM_NAMES:
        np.testing.assert_array_equal(p_zero[n], p_none[n], err_msg=n)
        np.testing.assert_array_equal(s_zero["exp_avg"][n], s_none["exp_avg"][n], err_msg=n)
        np.testing.assert_array_equal(p_one[n], p_once[n].get(), err_msg=n)     # the second step left out
        np.testing.assert_array_equal(s_one["exp_avg"][n], once.state_dict()["exp_avg"][n], err_msg=n)
        np.testing.assert_array_equal(s_one["exp_avg_sq"][n], once.state_dict()["exp_avg_sq"][n], err_msg=n)
        assert not np.array_equal(p_none[n], p_once[n].get()) or not grads[n].any(), n
