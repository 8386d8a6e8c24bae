"""select (cl/select.cl, ops/select.py): the Gaussians alive at t against the numpy reference
(reference/select.py) and project4d's own culling, the compaction and gather exactly, and the
selected step (render, adjoint, densification statistics, Adam on rows) against the full one."""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import pytest

from conftest import small
from endowave_cl.camera import Camera
from endowave_cl.gaussians import MARGINAL_CULL, PARAM_NAMES, Gaussians, upload
from endowave_cl.ops.adam import DeviceAdam
from endowave_cl.ops.project import project4d
from endowave_cl.ops.rasterize import accumulate_densify_stats
from endowave_cl.ops.select import LIVE_SLACK, gather_params, live_flags, select_live
from endowave_cl.reference.select import live_flags_ref, marginal_ref, select_live_ref
from endowave_cl.render import render, render_backward
from test_project4d import variant  # noqa: F401  (live_flags is written on project4d's lanes: each variant)


def _camera(w, h):
    return Camera(fx=0.9 * w, fy=0.9 * w, cx=w / 2, cy=h / 2, width=w, height=h)


def _short_lived(n, seed):
    """Gaussians with lifetimes from a hundredth to a third of the sequence, rotated in space-time, some
    of them behind the camera: at t = 0.5 some are alive, many are not."""
    g = Gaussians.random(n, seed=seed, center=(0, 0, 3), spread=1.2, scale=0.06)
    rng = np.random.default_rng(seed)
    g.scales[:, 3] = np.log(rng.uniform(0.01, 0.15, n)).astype(np.float32)
    g.means[: n // 10, 2] = -1.0
    return g


@pytest.mark.parametrize("n,seed", [(small(3000, 40), 0), (small(257, 24), 1)])
def test_live_flags_match_reference_and_keep_every_visible_gaussian(rt, variant, n, seed):
    g = _short_lived(n, seed)
    params = upload(rt, g)
    for t in (0.0, 0.37, 0.5, 1.0):
        flags = live_flags(rt, params, t).get()
        want = live_flags_ref(g, t, LIVE_SLACK)
        _, m = marginal_ref(g, t)
        near = np.abs(m / (MARGINAL_CULL * LIVE_SLACK) - 1) < 1e-4   # float32 against float64
        assert np.array_equal(flags[~near], want[~near]), t
        assert 0 < flags.sum() < n   # the scenes have both
        # a superset of what project4d keeps: every Gaussian it projects is selected
        radius = project4d(rt, params, _camera(64, 48), t).radius.get()
        assert np.all(flags[radius > 0] == 1), t


def test_live_flags_edge_cases(rt, variant):
    g = _short_lived(small(64, 20), 2)
    g.means[0, 3] = np.nan                    # NaN time: culled
    g.scales[1, :] = np.float32(-40.0)        # Sigma_tt below SIGMA_TT_MIN: culled
    g.quat_l[2, :] = 0.0                      # zero quaternion (clamped norm): no NaN
    g.scales[3, 3] = np.float32(3.0)          # lives for the whole sequence
    g.means[3, 3] = 0.5
    flags = live_flags(rt, upload(rt, g), 0.5).get()
    assert flags[0] == 0 and flags[1] == 0 and flags[3] == 1
    assert flags[2] == live_flags_ref(g, 0.5, LIVE_SLACK)[2]


@pytest.mark.oclgrind
@pytest.mark.parametrize("n", [small(500, 37), 1, 0])
def test_select_live_compacts_and_gathers_exactly(rt, n):
    g = _short_lived(n, 3) if n else Gaussians.empty()
    live = select_live(rt, upload(rt, g), 0.5)
    flags = live_flags(rt, upload(rt, g), 0.5).get()
    rows, want = select_live_ref(g, flags)
    assert live.n_full == n and len(live) == len(rows)
    assert np.array_equal(live.rows.get(), rows)
    for name in PARAM_NAMES:
        got = live.params[name].get()
        assert got.shape == want[name].shape and np.array_equal(got, want[name]), name


def _fresh_capacity(rt, share=None):
    """The runtime's LiveCapacity emptied, or having seen `share` (latest share = its capacity's / HEADROOM)."""
    from endowave_cl.ops.select import live_capacity
    policy = live_capacity(rt)
    policy.__init__()
    if share is not None:
        policy.observe(round(share * 1000), 1000)
    return policy


@pytest.mark.oclgrind
def test_select_live_unchecked_pads_to_its_capacity_and_reads_nothing(rt, monkeypatch):
    """check=False: the first selection reads L and sizes C = L exactly; later ones hold
    C = HEADROOM x the latest share x N rows with nothing read: the selected rows, then -1, whose
    gathered Gaussians project4d culls; L comes back without blocking and is what the next
    selection sizes from."""
    import endowave_cl.ops.select as sel
    n = small(500, 37)
    g = _short_lived(n, 3)
    params = upload(rt, g)
    rows_ref, want = select_live_ref(g, live_flags(rt, params, 0.5).get())
    L = len(rows_ref)
    assert 0 < L < n // 2
    policy = _fresh_capacity(rt)
    first = select_live(rt, params, 0.5, check=False)
    assert len(first) == L and first.count.value() == L and not first.overflowed
    assert policy.latest == L / n
    reads = []
    monkeypatch.setattr(cla.Array, "get", lambda self, *a, **k: reads.append(self) or np.zeros(0))
    live = select_live(rt, params, 0.5, check=False)
    monkeypatch.undo()
    assert reads == []
    cap = min(n, max(sel.MIN_ROWS, int(np.ceil(L / n * sel.HEADROOM * n))))
    assert len(live) == cap > L and live.count.capacity == cap
    rows = live.rows.get()
    assert np.array_equal(rows[:L], rows_ref) and np.all(rows[L:] == -1)
    for name in PARAM_NAMES:
        assert np.array_equal(live.params[name].get()[:L], want[name]), name
    assert live.count.value() == L and not live.overflowed
    radius = project4d(rt, live.params, _camera(64, 48), 0.5).radius.get()
    assert np.all(radius[L:] == 0)                         # the padding is culled
    for t in (0.0, 1.0):
        assert np.all(project4d(rt, live.params, _camera(64, 48), t).radius.get()[L:] == 0)


@pytest.mark.oclgrind
def test_select_live_unchecked_overflow_is_reported(rt, monkeypatch):
    """A capacity below L: the first C selected rows, and overflowed, never a silent truncation;
    check=True then reads L and gathers every row."""
    import endowave_cl.ops.select as sel
    monkeypatch.setattr(sel, "MIN_ROWS", 16)   # Oclgrind's small scene selects fewer than MIN_ROWS
    n = small(2000, 600)
    g = _short_lived(n, 3)
    params = upload(rt, g)
    rows_ref, _ = select_live_ref(g, live_flags(rt, params, 0.5).get())
    L = len(rows_ref)
    _fresh_capacity(rt, share=0.5 * L / n / sel.HEADROOM)   # C about L / 2
    live = select_live(rt, params, 0.5, check=False)
    cap = len(live)
    assert sel.MIN_ROWS <= cap < L and live.overflowed and live.count.value() == L
    assert np.array_equal(live.rows.get(), rows_ref[:cap])
    again = select_live(rt, params, 0.5, check=True)
    assert len(again) == L and not again.overflowed and np.array_equal(again.rows.get(), rows_ref)
    assert select_live(rt, params, 0.5, check=False).count.capacity >= L   # grown from the overflow


def test_select_live_unchecked_above_the_share_renders_every_row(rt):
    """check=False tests max_share on the latest share seen; the count is still read back without
    blocking, so that a share that falls is seen and selection resumes."""
    g = _short_lived(300, 8)
    params = upload(rt, g)
    policy = _fresh_capacity(rt, share=0.9)
    assert select_live(rt, params, 0.5, 0.5, check=False) is None
    assert policy.pending is not None
    rt.queue.finish()
    live = select_live(rt, params, 0.5, 0.5, check=False)   # the pending share (< 0.5) was seen first
    assert live is not None and policy.latest < 0.5


@pytest.mark.oclgrind
def test_gather_params_rows_in_any_order(rt):
    g = Gaussians.random(small(40, 12), seed=4, degree=2)   # sh rows of 81 floats: not whole float4s
    rows = np.array([5, 0, 5, len(g) - 1], np.int32)
    out = gather_params(rt, upload(rt, g), cla.to_device(rt.queue, rows), len(rows))
    for name in PARAM_NAMES:
        assert np.array_equal(out[name].get(), getattr(g, name)[rows]), name


def test_selected_render_and_adjoint_equal_the_full_ones(rt):
    """The same image bits; the adjoint's rows equal the full adjoint's at the selected rows, whose
    every other row is zero; the same densification statistics."""
    n, w, h = 400, 64, 48
    g = _short_lived(n, 5)
    cam = _camera(w, h)
    params = upload(rt, g)
    v = cla.to_device(rt.queue, np.random.default_rng(0).standard_normal((h, w, 6)).astype(np.float32))
    res = {}
    for select in (False, True):
        stats = {"grad_accum": cla.zeros(rt.queue, (n,), np.float32), "count": cla.zeros(rt.queue, (n,), np.int32),
                 "max_radius": cla.zeros(rt.queue, (n,), np.float32)}
        out = render(rt, params, cam, 0.5, 0.55, select=select)
        grads = render_backward(rt, params, out, v, densify_stats=stats, deterministic=True)
        res[select] = (out, {k: a.get() for k, a in grads.items()}, {k: a.get() for k, a in stats.items()})
    (full, gf, sf), (sel, gs, ss) = res[False], res[True]
    assert full.live is None and 0 < len(sel.live) < n
    assert np.array_equal(full.features.get(), sel.features.get())
    assert np.array_equal(full.alpha.get(), sel.alpha.get())
    rows = sel.live.rows.get()
    assert np.array_equal(full.proj.radius.get()[rows], sel.proj.radius.get())
    assert np.all(full.proj.radius.get()[np.setdiff1d(np.arange(n), rows)] == 0)
    for k in gf:
        assert gs[k].shape[0] == len(rows)
        assert np.array_equal(gf[k][rows], gs[k]), k
        rest = np.delete(gf[k], rows, axis=0)
        assert np.all(rest == 0), k
    for k in sf:
        assert np.array_equal(sf[k], ss[k]), k


def test_padded_render_adjoint_and_adam_equal_the_full_ones(rt):
    """render(select=True, check=False) on a padded rows buffer: the same image bits as the full
    render, the full adjoint's rows at the selected rows and zeros at the padding, the same
    densification statistics, and Adam over the padded rows the same as over every row."""
    n, w, h = 400, 64, 48
    g = _short_lived(n, 5)
    cam = _camera(w, h)
    v = cla.to_device(rt.queue, np.random.default_rng(0).standard_normal((h, w, 6)).astype(np.float32))
    lrs = {"means": 1e-3, "scales": 5e-3, "quat_l": 1e-3, "quat_r": 1e-3, "opacity": 0.05, "sh": 2.5e-3,
           "phase": 1e-3}
    res = {}
    for select in (False, True):
        params = upload(rt, g)
        opt = DeviceAdam(rt, params, lrs)
        stats = {"grad_accum": cla.zeros(rt.queue, (n,), np.float32), "count": cla.zeros(rt.queue, (n,), np.int32),
                 "max_radius": cla.zeros(rt.queue, (n,), np.float32)}
        _fresh_capacity(rt, share=0.45)
        out = render(rt, params, cam, 0.5, 0.55, select=select, check=False)
        assert not out.overflowed
        grads = render_backward(rt, params, out, v, densify_stats=stats, deterministic=True, sh_factors=True)
        got = {k: getattr(a, "factors", a).get() for k, a in grads.items()}
        opt.step({k[2:]: a for k, a in grads.items()}, visible=out.proj.radius,
                 rows=None if out.live is None else out.live.rows)
        res[select] = (out, got, {k: a.get() for k, a in stats.items()}, {k: a.get() for k, a in params.items()})
    (full, gf, sf, pf), (sel, gs, ss, ps) = res[False], res[True]
    L = sel.live.count.value()
    assert 0 < L < len(sel.live) < n
    assert np.array_equal(full.features.get(), sel.features.get())
    rows = sel.live.rows.get()[:L]
    for k in gf:
        assert np.array_equal(gf[k][rows], gs[k][:L]), k
        assert np.all(gs[k][L:] == 0), k
    for k in sf:
        assert np.array_equal(sf[k], ss[k]), k
    for k in pf:
        assert np.array_equal(pf[k], ps[k]), k


def test_select_leaves_a_mostly_alive_model_whole(rt):
    """Above SELECT_MAX_SHARE alive, render(select=True) renders every row (live None), the same bits."""
    from endowave_cl.ops.select import SELECT_MAX_SHARE
    g = _short_lived(300, 8)
    g.scales[:, 3] = np.float32(2.0)     # lives of several sequences before the 4D rotation
    params = upload(rt, g)
    assert select_live(rt, params, 0.5, SELECT_MAX_SHARE) is None
    assert len(select_live(rt, params, 0.5)) > SELECT_MAX_SHARE * 300
    out = render(rt, params, _camera(40, 32), 0.5, select=True)
    assert out.live is None
    assert np.array_equal(out.features.get(), render(rt, params, _camera(40, 32), 0.5).features.get())


def test_nothing_alive_renders_the_background_and_steps_nothing(rt):
    """Every Gaussian culled at t: zero rows selected, an empty image, empty gradients, and an
    Adam step on no rows that changes nothing but its count."""
    n = 50
    g = _short_lived(n, 9)
    g.means[:, 3] = 5.0                   # every Gaussian lives far after the sequence
    params = upload(rt, g)
    before = {k: a.get() for k, a in params.items()}
    out = render(rt, params, _camera(40, 32), 0.5, 0.6, select=True)
    assert out.live is not None and len(out.live) == 0 and out.n_isect == 0
    assert np.all(out.alpha.get() == 0)
    stats = {"grad_accum": cla.zeros(rt.queue, (n,), np.float32), "count": cla.zeros(rt.queue, (n,), np.int32),
             "max_radius": cla.zeros(rt.queue, (n,), np.float32)}
    grads = render_backward(rt, params, out, cla.zeros(rt.queue, (32, 40, 6), np.float32), densify_stats=stats,
                            sh_factors=True)
    assert all(getattr(v, "factors", v).shape[0] == 0 for v in grads.values())
    opt = DeviceAdam(rt, params, {"means": 1e-3, "scales": 1e-3, "quat_l": 1e-3, "quat_r": 1e-3, "opacity": 1e-2,
                                  "sh": 1e-3, "phase": 1e-3})
    opt.step({k[2:]: v for k, v in grads.items()}, visible=out.proj.radius, rows=out.live.rows)
    assert opt.step_count == 1
    for k, a in params.items():
        assert np.array_equal(a.get(), before[k]), k
    assert np.all(stats["count"].get() == 0)


@pytest.mark.oclgrind
def test_densify_stats_on_rows_match_the_full_kernel(rt):
    n, L = small(300, 30), small(90, 9)
    rng = np.random.default_rng(1)
    rows = np.sort(rng.choice(n, L, replace=False)).astype(np.int32)
    v2d = rng.standard_normal((L, 2)).astype(np.float32)
    radius = rng.integers(0, 4, L).astype(np.int32)
    full_v = np.zeros((n, 2), np.float32)
    full_v[rows] = v2d
    full_r = np.zeros(n, np.int32)
    full_r[rows] = radius
    out = []
    pad = 5   # padding rows (-1, radius 0) after the selected ones, as select_live(check=False) leaves them
    rows_p = np.concatenate([rows, np.full(pad, -1, np.int32)])
    v2d_p = np.concatenate([v2d, rng.standard_normal((pad, 2)).astype(np.float32)])
    radius_p = np.concatenate([radius, np.zeros(pad, np.int32)])
    for r_arg, vv, rr in ((None, full_v, full_r), (rows, v2d, radius), (rows_p, v2d_p, radius_p)):
        stats = [cla.to_device(rt.queue, a) for a in (np.full(n, 0.5, np.float32), np.ones(n, np.int32),
                                                        np.full(n, 2.0, np.float32))]
        accumulate_densify_stats(rt, cla.to_device(rt.queue, vv), cla.to_device(rt.queue, rr), 40, 30, *stats,
                                 rows=None if r_arg is None else cla.to_device(rt.queue, r_arg))
        out.append([a.get() for a in stats])
    for a, b, c in zip(*out):
        assert np.array_equal(a, b) and np.array_equal(a, c)


def _adam_pair(rt, g, lrs):
    params = {s: upload(rt, g) for s in ("full", "rows")}
    return params, {s: DeviceAdam(rt, params[s], lrs) for s in params}


@pytest.mark.oclgrind
@pytest.mark.parametrize("factored,degree", [(False, 1), (True, 1), (True, 2)])
def test_adam_on_rows_equals_adam_with_the_culled_rows_frozen(rt, factored, degree):
    """DeviceAdam.step(rows=...) with compact gradients: the same parameters and moments as the
    full step whose gradient is zero and whose visibility is 0 off the rows, over several steps."""
    from endowave_cl.ops.project import ShGradFactors, sh_factor_width
    n = small(200, 21)
    g = Gaussians.random(n, seed=6, degree=degree)   # sh rows of 36 floats (whole runs of 4) and 81
    lrs = {"means": 1e-3, "means_t": 2e-3, "scales": 5e-3, "quat_l": 1e-3, "quat_r": 2e-3, "opacity": 0.05,
           "sh": 2.5e-3, "phase": 4e-3}
    params, opt = _adam_pair(rt, g, lrs)
    rng = np.random.default_rng(2)
    nt, K = g.sh.shape[1] - 1, g.sh.shape[2]
    for step in range(3):
        rows = np.sort(rng.choice(n, n // 3, replace=False)).astype(np.int32)
        vis = rng.integers(0, 3, len(rows)).astype(np.int32)    # some selected rows are culled too
        comp = {name: rng.standard_normal((len(rows),) + a.shape[1:]).astype(np.float32)
                for name, a in g.as_dict().items()}
        if factored:
            comp["sh"] = rng.standard_normal((len(rows), sh_factor_width(nt, K))).astype(np.float32)
        full = {name: np.zeros((n,) + a.shape[1:], np.float32) for name, a in comp.items()}
        for name in comp:
            full[name][rows] = comp[name]
        full_vis = np.zeros(n, np.int32)
        full_vis[rows] = vis

        def dev(d):
            out = {k: cla.to_device(rt.queue, a) for k, a in d.items()}
            if factored:
                out["sh"] = ShGradFactors(out["sh"], nt, K)
            return out
        opt["full"].step(dev(full), visible=cla.to_device(rt.queue, full_vis))
        pad = 3   # padding rows (-1, not visible) after the selected ones, as select_live(check=False) leaves them
        comp = {k: np.concatenate([a, np.ones((pad,) + a.shape[1:], np.float32)]) for k, a in comp.items()}
        rows_p = np.concatenate([rows, np.full(pad, -1, np.int32)])
        vis_p = np.concatenate([vis, np.zeros(pad, np.int32)])
        opt["rows"].step(dev(comp), visible=cla.to_device(rt.queue, vis_p), rows=cla.to_device(rt.queue, rows_p))
    a, b = opt["full"].state_dict(), opt["rows"].state_dict()
    for name in PARAM_NAMES:
        np.testing.assert_array_equal(params["full"][name].get(), params["rows"][name].get(), err_msg=name)
        np.testing.assert_array_equal(a["exp_avg"][name], b["exp_avg"][name], err_msg=name)
        np.testing.assert_array_equal(a["exp_avg_sq"][name], b["exp_avg_sq"][name], err_msg=name)
    assert a["step"] == b["step"] == 3


def test_adam_rows_argument_errors(rt):
    from endowave_cl.errors import EndowaveError
    g = Gaussians.random(10, seed=0)
    params = upload(rt, g)
    opt = DeviceAdam(rt, params, {"means": 1e-3, "scales": 1e-3, "quat_l": 1e-3, "quat_r": 1e-3, "opacity": 1e-2,
                                  "sh": 1e-3, "phase": 1e-3})
    rows = cla.to_device(rt.queue, np.array([1, 4], np.int32))
    grads = {k: cla.zeros(rt.queue, a.shape, np.float32) for k, a in g.as_dict().items()}   # full, not compact
    with pytest.raises(EndowaveError, match="gradient of 'means' has shape"):
        opt.step(grads, rows=rows)
    with pytest.raises(EndowaveError, match="rows must be int32"):
        opt.step(grads, rows=cla.to_device(rt.queue, np.arange(11, dtype=np.int32)))
    assert opt.step_count == 0


@pytest.mark.slow
def test_training_with_and_without_selection_gives_the_same_bits(rt, tiny_scene, tmp_path, monkeypatch):
    """Trainer steps (training frames, in-between steps, densification) on the selected rows end
    with the same parameters and moments as steps over every Gaussian ($ENDOWAVE_NO_SELECT).
    Bit equality needs the deterministic adjoint: a GPU's default (float atomics) sums in an order
    that changes from one run to the next, with or without select."""
    from conftest import tiny_config
    from endowave_cl.data.scene import load_scene
    from endowave_cl.ops.select import ENV_NO_SELECT, SELECT_MAX_SHARE
    from endowave_cl.train.trainer import Trainer
    scene = load_scene(tiny_scene)
    cfg = dict(iterations=60, init_points=2000, densify_from=20, densify_every=20, densify_until=40,
               init_time_scale=0.05, eval_every=0, deterministic=True)
    states = []
    for off in (True, False):
        if off:
            monkeypatch.setenv(ENV_NO_SELECT, "1")
        else:
            monkeypatch.delenv(ENV_NO_SELECT, raising=False)
        tr = Trainer(scene, tiny_config(**cfg), tmp_path / f"run{int(off)}", rt, log=lambda s: None)
        assert tr.select_live is (not off)
        tr.train(progress=False)
        assert select_live(rt, tr.params, 0.5, SELECT_MAX_SHARE) is not None   # the steps ran on rows
        states.append(({k: a.get() for k, a in tr.params.items()}, tr.adam.state_dict()))
    (p0, s0), (p1, s1) = states
    for name in PARAM_NAMES:
        assert np.array_equal(p0[name], p1[name]), name
        assert np.array_equal(s0["exp_avg"][name], s1["exp_avg"][name]), name
