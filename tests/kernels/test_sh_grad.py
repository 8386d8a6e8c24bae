"""The SH-coefficient gradient as per-Gaussian factors (cl/sh_grad.h): project4d_bwd's factored
output against its full v_sh, DeviceAdam on the factors against Adam on the full gradient, and
the NaN guard on the factors.  Every comparison is exact (bit for bit)."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import small
from endowave_cl.camera import Camera
from endowave_cl.gaussians import PARAM_NAMES, Gaussians, upload
from endowave_cl.ops.adam import DeviceAdam
from endowave_cl.ops.project import ShGradFactors, project4d, project4d_bwd
from endowave_cl.render import render, render_backward
from test_project4d import lane_scene, variant  # noqa: F401  (variant: the project4d kernel variants)

LRS = {"means": 1.6e-4, "means_t": 1e-3, "scales": 5e-3, "quat_l": 1e-3, "quat_r": 2e-3,
       "opacity": 0.05, "sh": 2.5e-3, "phase": 4e-3}


def same_bits(a, b) -> bool:
    a, b = np.asarray(a, np.float32), np.asarray(b, np.float32)
    return a.shape == b.shape and np.array_equal(a.view(np.uint32), b.view(np.uint32))


def clamp_some(g: Gaussians, every: int = 5) -> Gaussians:
    """Rows whose colour is clamped at 0 (their colour gradient does not pass)."""
    g.sh[::every, 0, 0, :] = -5.0
    return g


def adjoint_both(rt, g, cam, t, t_flow, seed):
    """project4d_bwd of the same inputs with v_sh in full and as factors."""
    import pyopencl.array as cla
    n = len(g)
    rng = np.random.default_rng(seed)
    prm = upload(rt, g)
    p = project4d(rt, prm, cam, t, t_flow)
    dv = [cla.to_device(rt.queue, rng.standard_normal(s).astype(np.float32))
          for s in ((n, 2), (n, 3), (n,), (n, 6))]
    full = project4d_bwd(rt, prm, cam, t, t_flow, p, *dv)
    fac = project4d_bwd(rt, prm, cam, t, t_flow, p, *dv, sh_factors=True)
    return full, fac, p.radius.get()


def check_factors(full, fac, radius):
    assert isinstance(fac["v_sh"], ShGradFactors)
    assert fac["v_sh"].shape == full["v_sh"].shape
    for k in full:
        assert same_bits(fac[k].get(), full[k].get()), k
    f = fac["v_sh"].factors.get()
    assert (f[radius <= 0] == 0).all()


@pytest.mark.parametrize("n", [3, 16, 33, 71])
@pytest.mark.parametrize("t_flow", [None, 0.58])
def test_factors_equal_full_v_sh(rt, variant, n, t_flow):  # noqa: F811
    g = clamp_some(lane_scene(n, 0.5, seed=n))
    g.scales[g.scales[:, 0] == 60.0] = -40.0   # (as test_project4d.test_lanes_forward_and_adjoint)
    cam = Camera(150.0, 160.0, 80.0, 60.0, 160, 120)
    full, fac, radius = adjoint_both(rt, g, cam, 0.5, t_flow, seed=n)
    assert (radius > 0).any() and (n < 8 or (radius == 0).any())
    assert np.abs(full["v_sh"].get()).max() > 0
    check_factors(full, fac, radius)


@pytest.mark.parametrize("degree,nt", [(0, 0), (1, 1), (2, 2)])
def test_factors_equal_full_v_sh_other_sizes(rt, variant, degree, nt):  # noqa: F811
    g = clamp_some(Gaussians.random(small(50, 18), seed=4, degree=degree, nt=nt))
    g.means[0, 2] = -1.0   # culled
    cam = Camera(150.0, 160.0, 80.0, 60.0, 160, 120)
    full, fac, radius = adjoint_both(rt, g, cam, 0.5, 0.55, seed=4)
    check_factors(full, fac, radius)


@pytest.mark.oclgrind
def test_factors_tiny_oclgrind(rt, variant):  # noqa: F811
    g = clamp_some(lane_scene(21, 0.5, seed=2))
    g.scales[g.scales[:, 0] == 60.0] = -40.0
    cam = Camera(150.0, 160.0, 80.0, 60.0, 160, 120)
    full, fac, radius = adjoint_both(rt, g, cam, 0.5, 0.56, seed=2)
    check_factors(full, fac, radius)


def train_both(rt, g, steps, lrs, size=(48, 40), skip_culled=False):
    """`steps` Adam steps on rendered gradients, once with v_sh in full and once as factors, from the
    same parameters: both runs' parameters and moments.  skip_culled: Adam leaves the step's culled
    Gaussians alone (visible = the projected radius)."""
    import pyopencl.array as cla
    w, h = size
    cam = Camera(0.9 * w, 0.9 * w, w / 2, h / 2, w, h)
    rng = np.random.default_rng(0)
    v_feats = [rng.standard_normal((h, w, 6)).astype(np.float32) for _ in range(steps)]
    runs = []
    for factored in (False, True):
        params = upload(rt, g)
        opt = DeviceAdam(rt, params, lrs)
        for s in range(steps):
            out = render(rt, params, cam, 0.4 + 0.05 * s, 0.5 + 0.05 * s)
            grads = render_backward(rt, params, out, cla.to_device(rt.queue, v_feats[s]), deterministic=True,
                                    sh_factors=factored)
            assert isinstance(grads["v_sh"], ShGradFactors) == factored
            opt.step({name[2:]: a for name, a in grads.items()}, visible=out.proj.radius if skip_culled else None)
        st = opt.state_dict()
        runs.append({n: (params[n].get(), st["exp_avg"][n], st["exp_avg_sq"][n]) for n in PARAM_NAMES})
    return runs


def scene(n, degree=3, nt=2):
    g = clamp_some(Gaussians.random(n, seed=3, degree=degree, nt=nt, spread=1.2, scale=0.08), every=7)
    g.means[: n // 10, 2] = -1.0   # behind the camera: culled
    return g


@pytest.mark.parametrize("degree,nt,n", [(3, 2, 120), (2, 2, 120), (1, 0, 120), (1, 2, 120), (1, 2, 121),
                                         (0, 2, 123)])
def test_adam_on_factors_equals_adam_on_full_gradient(rt, degree, nt, n):
    """Adam's factored sh group takes the Gaussians in blocks of sh_gaussians_per_item (2 at degree
    1, 8 at degree 0); an N that is not a multiple leaves a short last block."""
    old, new = train_both(rt, scene(small(n, 20 + n % 2), degree, nt), 3, LRS)
    for n in PARAM_NAMES:
        for what, a, b in zip(("param", "exp_avg", "exp_avg_sq"), old[n], new[n]):
            assert same_bits(a, b), (n, what)
    assert not same_bits(old["sh"][1], np.zeros_like(old["sh"][1]))   # the SH did get gradients


@pytest.mark.parametrize("degree", [3, 1])
def test_adam_on_factors_skip_culled(rt, degree):
    """Adam with the culled rows frozen: the factored and the full SH gradient give the same bits,
    and a Gaussian culled at every step (behind the camera) keeps its parameters and zero moments.
    At degree 1 a work-item's block of two Gaussians can hold one culled and one live row (the
    culled ones are every 10th, by the first tenth's indices and the clamp's)."""
    g = scene(small(121, 21), degree)
    g.means[1::10, 2] = -1.0   # odd rows culled too: blocks that mix a culled and a live row
    old, new = train_both(rt, g, 3, LRS, skip_culled=True)
    for n in PARAM_NAMES:
        for what, a, b in zip(("param", "exp_avg", "exp_avg_sq"), old[n], new[n]):
            assert same_bits(a, b), (n, what)
    behind = g.means[:, 2] < 0
    for n in PARAM_NAMES:
        p, m, v = new[n]
        assert same_bits(p[behind], getattr(g, n)[behind].astype(np.float32)), n
        assert not m[behind].any() and not v[behind].any(), n
        assert m[~behind].any(), n


def test_adam_on_factors_frozen_sh(rt):
    lrs = dict(LRS, sh_rest=0.0)   # only the DC coefficient moves
    g = scene(small(60, 20))
    old, new = train_both(rt, g, 2, lrs)
    for n in PARAM_NAMES:
        for a, b in zip(old[n], new[n]):
            assert same_bits(a, b), n
    sh, m, _ = new["sh"]
    assert same_bits(sh.reshape(len(g), -1)[:, 3:], g.sh.reshape(len(g), -1)[:, 3:])
    assert (m.reshape(len(g), -1)[:, 3:] == 0).all() and m.reshape(len(g), -1)[:, :3].any()


@pytest.mark.oclgrind
def test_adam_on_factors_tiny_oclgrind(rt):
    old, new = train_both(rt, scene(20), 2, LRS, size=(32, 24))
    for n in PARAM_NAMES:
        for a, b in zip(old[n], new[n]):
            assert same_bits(a, b), n


@pytest.mark.oclgrind
@pytest.mark.parametrize("bad", [None, np.nan, np.inf])
def test_guard_checks_the_factors(rt, bad):
    """A non-finite colour gradient of a visible Gaussian makes its factors and its full v_sh
    non-finite: the guard on the factors refuses the step as the guard on v_sh would."""
    import pyopencl.array as cla

    from endowave_cl.ops.util import any_nonfinite
    g = Gaussians.random(12, seed=1)
    g.means[:, 3] = 0.5
    cam = Camera(150.0, 160.0, 80.0, 60.0, 160, 120)
    prm = upload(rt, g)
    p = project4d(rt, prm, cam, 0.5, None)
    radius = p.radius.get()
    i = int(np.flatnonzero(radius > 0)[0])
    vf = np.zeros((12, 6), np.float32)
    vf[:, :3] = 1.0
    if bad is not None:
        vf[i, 1] = bad
    z = [cla.zeros(rt.queue, s, np.float32) for s in ((12, 2), (12, 3), (12,))]
    dvf = cla.to_device(rt.queue, vf)
    full = project4d_bwd(rt, prm, cam, 0.5, None, p, *z, dvf)["v_sh"]
    fac = project4d_bwd(rt, prm, cam, 0.5, None, p, *z, dvf, sh_factors=True)["v_sh"]
    assert any_nonfinite(rt, [full]) == (bad is not None)
    assert any_nonfinite(rt, [fac]) == (bad is not None)


def test_train_steps_equal_the_full_gradient_path(rt, tiny_scene, tmp_path, monkeypatch):
    """Trainer.train_step (factored SH gradient) against the same steps with v_sh in full."""
    import endowave_cl.train.trainer as trainer_module
    from conftest import tiny_config
    from endowave_cl.data.scene import load_scene
    from endowave_cl.gaussians import download
    scene = load_scene(tiny_scene)
    real = trainer_module.render_backward
    runs = []
    for factored in (True, False):
        if not factored:
            monkeypatch.setattr(trainer_module, "render_backward",
                                lambda *a, **kw: real(*a, **{**kw, "sh_factors": False}))
        tr = trainer_module.Trainer(scene, tiny_config(iterations=10, init_points=500, use_flow=True),
                                    tmp_path / f"run{int(factored)}", rt, log=lambda s: None)
        for k in scene.train_indices[:4]:
            tr.train_step(k)
        st = tr.adam.state_dict()
        runs.append((download(tr.params).as_dict(), st["exp_avg"], st["exp_avg_sq"]))
    for n in PARAM_NAMES:
        for a, b in zip(runs[0], runs[1]):
            assert same_bits(a[n], b[n]), n
