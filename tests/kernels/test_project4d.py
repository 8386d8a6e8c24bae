"""project4d: OpenCL kernel vs torch reference (forward and adjoint), and the 4D geometry itself."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from conftest import small
from endowave_cl.camera import Camera
from endowave_cl.gaussians import MARGINAL_CULL, Gaussians, upload
from endowave_cl.ops.project import ENV_VARIANT, ENV_VEC_WIDTH, project4d, project4d_bwd, project_lanes
from endowave_cl.layout import ALPHA_MIN
from endowave_cl.reference.project import (TIGHT_OPAC_SLACK, condition_at, covariance4d, project4d_ref,
                                           rotation4d, sh_basis, tight_extent)

FLOAT_OUTS = ("means2d", "conic", "depth", "opac", "features")
INT_OUTS = ("radius", "rect", "tiles_touched")

# Every kernel variant (ops/project.py): the scalar kernels (the GPU path) and the vector ones at
# each lane count (the CPU path; scenes with fewer Gaussians than lanes run the scalar kernels).
VARIANT_PARAMS = ["scalar", "vector4", "vector8", "vector16"]


@pytest.fixture(params=VARIANT_PARAMS)
def variant(request, monkeypatch, rt):
    """Run the test with each project4d variant, forward and adjoint."""
    name = request.param
    monkeypatch.setenv(ENV_VARIANT, name[:6])
    monkeypatch.delenv(ENV_VEC_WIDTH, raising=False)
    if name != "scalar":
        monkeypatch.setenv(ENV_VEC_WIDTH, name[6:])
    assert project_lanes(rt) == (0 if name == "scalar" else int(name[6:]))
    return name


def look_camera(seed: int, width=200, height=150) -> Camera:
    """A camera at a random position near the origin looking at (0, 0, 3), where the scenes are."""
    rng = np.random.default_rng(seed)
    eye = np.array([0.0, 0.0, 0.0]) + 0.3 * rng.uniform(-1, 1, 3)
    fwd = np.array([0.0, 0.0, 3.0]) - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(np.array([0.0, 1.0, 0.0]) + 0.1 * rng.uniform(-1, 1, 3), fwd)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd])          # world -> camera rows (x right, y down, z forward)
    V = np.eye(4)
    V[:3, :3] = R
    V[:3, 3] = -R @ eye
    return Camera(1.1 * width, 1.1 * width, width / 2 + 3.3, height / 2 - 2.1, width, height, V)


def torch_params(g: Gaussians, dtype=torch.float32):
    return {k: torch.from_numpy(v.copy()).to(dtype) for k, v in g.as_dict().items()}


def run_both(rt, g, cam, t, t_flow, channels=6):
    p = project4d(rt, upload(rt, g), cam, t, t_flow, channels)
    r = project4d_ref(torch_params(g), cam, t, t_flow, channels)
    return {f: getattr(p, f).get() for f in FLOAT_OUTS + INT_OUTS}, {f: r[f].numpy() for f in r}


def assert_close(a, b, rtol, atol, what):
    """|a - b| <= atol + rtol |b| elementwise; atol may be an array broadcast against b."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    assert a.shape == b.shape, (what, a.shape, b.shape)
    err = np.abs(a - b) - (atol + rtol * np.abs(b))
    if err.size and not (err <= 0).all():
        i = np.unravel_index(np.argmax(err), err.shape)
        raise AssertionError(f"{what}: {int((err > 0).sum())} of {err.size} differ; worst at {i}: "
                             f"{a[i]!r} vs {b[i]!r}")


def at_rounding_boundary(r, rel=1e-5, tile_abs=1e-5):
    """Rows whose integer outputs sit on a float rounding boundary: 3 sqrt(lambda_max) (before ceil)
    within rel of an integer, or (mean2d -+ radius) / 16 (before floor / ceil) within tile_abs.  The kernel and torch
    sum the same float32 products in different orders (and may fuse multiply-adds), so a value a few
    ulps from an integer can round either way there; nowhere else may integers differ."""
    q = r["conic"].astype(np.float64)
    det = q[:, 0] * q[:, 2] - q[:, 1] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        a, c = q[:, 2] / det, q[:, 0] / det          # cov2d = inverse(conic)
        b = -q[:, 1] / det
        mid = 0.5 * (a + c)
        v = 3.0 * np.sqrt(mid + np.sqrt(np.maximum(mid * mid - (a * c - b * b), 0.0)))
    near = np.abs(v - np.round(v)) <= rel * np.abs(v)
    rad = r["radius"].astype(np.float64)
    # the tight rect's extents (reference/project.py tight_extent) and its opacity test
    ex, ey, _ = tight_extent(torch.from_numpy(r["opac"]), torch.from_numpy(a.astype(np.float32)),
                             torch.from_numpy(c.astype(np.float32)), torch.from_numpy(rad.astype(np.float32)))
    for j, ext in enumerate((ex.numpy().astype(np.float64), ey.numpy().astype(np.float64))):
        for sgn in (-1.0, 1.0):
            for half in (rad, ext):
                e = (r["means2d"][:, j].astype(np.float64) + sgn * half) / 16.0
                near |= np.abs(e - np.round(e)) <= tile_abs
    near |= np.abs(r["opac"].astype(np.float64) / ALPHA_MIN - TIGHT_OPAC_SLACK) <= rel
    return near & (r["radius"] > 0)


def assert_forward_close(k, r):
    ok_rows = ~at_rounding_boundary(r)
    assert ok_rows.sum() >= 0.99 * len(ok_rows)
    for f in INT_OUTS:
        np.testing.assert_array_equal(k[f][ok_rows], r[f][ok_rows], err_msg=f)
        assert (np.abs(k[f].astype(np.int64) - r[f]).reshape(len(ok_rows), -1).max(1, initial=0)
                <= np.where(ok_rows, 0, 1 if f != "tiles_touched" else 10 ** 6)).all(), f
    for f in ("means2d", "conic", "depth", "opac"):
        b = r[f].astype(np.float64)
        # atol: 1e-4 of the largest magnitude of the column (conic b can be ~0 next to large a, c)
        scale = np.abs(b).reshape(len(b), -1).max(0) if len(b) else 0.0
        assert_close(k[f].reshape(len(b), -1), b.reshape(len(b), -1), 1e-4,
                     1e-4 * np.maximum(scale, 1e-3), f)
    fk, fr = k["features"].astype(np.float64), r["features"].astype(np.float64)
    C = fr.shape[1]
    np.testing.assert_allclose(fk[:, :3], fr[:, :3], rtol=1e-4, atol=1e-4, err_msg="colour")
    if C > 3:
        np.testing.assert_allclose(fk[:, 3], fr[:, 3], rtol=1e-4, atol=1e-6, err_msg="depth channel")
    if C > 5:
        # flow = difference of two projections: its float32 error follows the projected coordinates
        atol = 1e-4 * (1.0 + np.abs(r["means2d"]) + np.abs(fr[:, 4:6]))
        assert_close(fk[:, 4:6], fr[:, 4:6], 1e-4, atol, "flow")
    for f in FLOAT_OUTS:
        assert np.isfinite(k[f]).all(), f


# ---------------------------------------------------------------------------------------------
# forward: kernel vs reference

@pytest.mark.parametrize("n,seed,t,t_flow", [(1, 0, 0.5, None), (37, 1, 0.3, 0.35), (500, 2, 0.7, 0.6),
                                             (1000, 3, 0.0, 1.0)])
def test_forward_matches_reference(rt, variant, n, seed, t, t_flow):
    g = Gaussians.random(small(n, 7), seed=seed)
    g.means[:2, 3] = t              # the first two at their temporal peak, so N = 1 is visible too
    cam = look_camera(seed)
    k, r = run_both(rt, g, cam, t, t_flow)
    assert (r["radius"] > 0).sum() > 0.3 * len(g)   # the scene is mostly visible: a real comparison
    assert_forward_close(k, r)
    if t_flow is None:
        assert (k["features"][:, 4:] == 0).all()


@pytest.mark.parametrize("degree,nt,channels", [(0, 0, 3), (1, 1, 4), (2, 3, 6), (3, 2, 8)])
def test_forward_other_sizes(rt, variant, degree, nt, channels):
    g = Gaussians.random(small(70, 5), seed=11, degree=degree, nt=nt)
    k, r = run_both(rt, g, look_camera(3), 0.45, 0.5, channels)
    assert k["features"].shape == (len(g), channels)
    assert_forward_close(k, r)


@pytest.mark.oclgrind
def test_forward_tiny_oclgrind(rt, variant):
    g = Gaussians.random(7, seed=4)
    g.means[0, 2] = -1.0            # one behind the camera
    k, r = run_both(rt, g, look_camera(4, 40, 24), 0.5, 0.55)
    assert_forward_close(k, r)


def test_empty_scene(rt, variant):
    g = Gaussians.empty()
    p = project4d(rt, upload(rt, g), look_camera(0), 0.5, 0.6)
    assert p.means2d.shape == (0, 2) and p.features.shape == (0, 6) and p.rect.shape == (0, 4)
    r = project4d_ref(torch_params(g), look_camera(0), 0.5, 0.6)
    assert r["means2d"].shape == (0, 2) and r["radius"].shape == (0,)


# ---------------------------------------------------------------------------------------------
# the 4D geometry

def hamilton(p, q):
    """Quaternion product p * q, (w, x, y, z), numpy."""
    a1, b1, c1, d1 = p
    a2, b2, c2, d2 = q
    return np.array([a1 * a2 - b1 * b2 - c1 * c2 - d1 * d2, a1 * b2 + b1 * a2 + c1 * d2 - d1 * c2,
                     a1 * c2 - b1 * d2 + c1 * a2 + d1 * b2, a1 * d2 + b1 * c2 - c1 * b2 + d1 * a2])


def test_rotation4d_is_a_rotation_and_equals_quaternion_sandwich():
    rng = np.random.default_rng(0)
    ql, qr = rng.standard_normal((20, 4)), rng.standard_normal((20, 4))
    R = rotation4d(torch.from_numpy(ql), torch.from_numpy(qr)).numpy()
    for i in range(20):
        np.testing.assert_allclose(R[i] @ R[i].T, np.eye(4), atol=1e-12)
        assert abs(np.linalg.det(R[i]) - 1.0) < 1e-12
        ul, ur = ql[i] / np.linalg.norm(ql[i]), qr[i] / np.linalg.norm(qr[i])
        # independent construction: column j is q_l * e_j * q_r
        cols = [hamilton(hamilton(ul, e), ur) for e in np.eye(4)]
        np.testing.assert_allclose(R[i], np.stack(cols, 1), atol=1e-12)


def test_rotation4d_known_xt_plane_rotation():
    # q_l = q_r = (cos(theta/2), 0, 0, sin(theta/2)) = exp(k theta/2) on both sides: the (1, k) plane,
    # i.e. the (x, t) plane, turns by theta/2 twice, while the (i, j) = (y, z) plane turns by
    # +theta/2 and then -theta/2 (k i = j but i k = -j), so it stays fixed.
    theta = 0.7
    q = torch.tensor([[math.cos(theta / 2), 0.0, 0.0, math.sin(theta / 2)]], dtype=torch.float64)
    R = rotation4d(q, 3.0 * q)[0].numpy()   # unnormalised input on purpose
    c, s = math.cos(theta), math.sin(theta)
    expected = np.array([[c, 0, 0, -s], [0, 1, 0, 0], [0, 0, 1, 0], [s, 0, 0, c]])
    np.testing.assert_allclose(R, expected, atol=1e-12)


def xt_gaussian(theta, sx, st, mean):
    """Gaussians with one Gaussian rotated by theta in the (x, t) plane (see the test above)."""
    g = Gaussians.random(1, seed=0)
    q = np.array([math.cos(theta / 2), 0.0, 0.0, math.sin(theta / 2)])
    g.quat_l[0] = q
    g.quat_r[0] = q
    g.scales[0] = np.log([sx, 0.05, 0.05, st])
    g.means[0] = mean
    g.opacity[0] = 2.0
    return g


def test_known_velocity_position_and_flow(rt, variant):
    theta, sx, st = 0.6, 0.05, 0.4
    c, s = math.cos(theta), math.sin(theta)
    # Sigma = R diag(sx^2, ., ., st^2) R^T in the (x, t) plane, R = [[c, -s], [s, c]]:
    sxt = c * s * (sx ** 2 - st ** 2)
    stt = s * s * sx ** 2 + c * c * st ** 2
    v = sxt / stt                                        # world units per unit time along x
    mean = np.array([0.1, -0.05, 3.0, 0.5])
    g = xt_gaussian(theta, sx, st, mean)
    cam = Camera(150.0, 160.0, 80.0, 60.0, 160, 120)     # identity pose
    t1, t2 = 0.45, 0.6
    p = project4d(rt, upload(rt, g), cam, t1, t2)
    p2 = project4d(rt, upload(rt, g), cam, t2, None)
    for proj, tt in ((p, t1), (p2, t2)):
        x = mean[0] + v * (tt - mean[3])
        pred = np.array([cam.fx * x / mean[2] + cam.cx, cam.fy * mean[1] / mean[2] + cam.cy])
        np.testing.assert_allclose(proj.means2d.get()[0], pred, rtol=1e-5)
        m = math.exp(-0.5 * (tt - mean[3]) ** 2 / stt)
        np.testing.assert_allclose(proj.opac.get()[0], m / (1 + math.exp(-2.0)), rtol=1e-5)
    flow = p.features.get()[0, 4:6]
    np.testing.assert_allclose(flow, p2.means2d.get()[0] - p.means2d.get()[0], rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(flow, [cam.fx * v * (t2 - t1) / mean[2], 0.0], rtol=1e-4, atol=1e-4)
    assert abs(flow[0]) > 1.0                            # it really moves


def test_conditional_finite_differences():
    torch.manual_seed(0)
    g = Gaussians.random(5, seed=3)
    P = torch_params(g, torch.float64)
    P["means"].requires_grad_(True)
    for name in ("scales", "quat_l", "quat_r"):
        P[name].requires_grad_(True)

    def f(means, scales, ql, qr):
        mu, cov, m = condition_at(means, covariance4d(scales, ql, qr), 0.4)
        return mu, cov, m

    assert torch.autograd.gradcheck(f, (P["means"], P["scales"], P["quat_l"], P["quat_r"]),
                                    eps=1e-6, atol=1e-6, rtol=1e-5)


def test_sh_basis_orthonormal():
    # Monte-Carlo over the sphere: E[Y_a Y_b] = delta_ab / (4 pi) for the real orthonormal basis
    rng = np.random.default_rng(0)
    d = rng.standard_normal((400000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    Y = sh_basis(torch.from_numpy(d), 3).numpy()
    gram = 4 * np.pi * Y.T @ Y / len(d)
    np.testing.assert_allclose(gram, np.eye(16), atol=0.02)


# ---------------------------------------------------------------------------------------------
# culling

def test_culling_rules(rt, variant):
    g = Gaussians.random(8, seed=5, scale=0.02)
    cam = look_camera(7, 160, 120)
    t = 0.5
    g.means[:, 3] = t                 # all at their temporal peak: m = 1
    g.means[0, :3] = [0.0, 0.0, -2.0]                           # behind the camera
    g.means[1, :3] = [50.0, 0.0, 3.0]                           # far off-screen
    g.means[2, 3] = t + 10.0                                    # marginal ~ 0
    g.scales[3] = -40.0                                         # degenerate: tiny (Sigma_tt ~ 0)
    g.scales[4] = 60.0                                          # degenerate: huge (overflows)
    g.means[5, 3] = t + 2.5 * np.exp(g.scales[5, 3])            # m = exp(-0.5 2.5^2) = 0.044 < 0.05 ...
    g.quat_l[5] = g.quat_r[5] = [1, 0, 0, 0]                    # ... with Sigma_tt = s_t^2
    g.means[6, 3] = t + 2.4 * np.exp(g.scales[6, 3])            # m = 0.056: kept
    g.quat_l[6] = g.quat_r[6] = [1, 0, 0, 0]
    g.means[7, :3] = [0.0, 0.0, 3.0]                            # ordinary, kept
    assert math.exp(-0.5 * 2.5 ** 2) < MARGINAL_CULL < math.exp(-0.5 * 2.4 ** 2)
    k, r = run_both(rt, g, cam, t, t + 0.1)
    assert_forward_close(k, r)
    expect_kept = np.array([0, 0, 0, 0, 0, 0, 1, 1], bool)
    for out in (k, r):
        kept = out["radius"] > 0
        np.testing.assert_array_equal(kept, expect_kept)
        for f in FLOAT_OUTS:
            assert np.isfinite(out[f]).all()
            assert (out[f][~kept] == 0).all(), f
        assert (out["rect"][~kept] == 0).all() and (out["tiles_touched"][~kept] == 0).all()


# ---------------------------------------------------------------------------------------------
# adjoint: kernel vs torch autograd of the reference (float64, so it is the exact derivative)

GRAD_NAMES = ("means", "scales", "quat_l", "quat_r", "opacity", "sh", "phase")


def make_culled(g: Gaussians, t: float):
    """Turn a few rows into Gaussians the forward culls (so their gradient must be 0)."""
    if len(g) >= 4:
        g.means[0, 2] = -1.0                  # behind the camera
        g.means[1, 3] = t + 20.0              # marginal ~ 0
        g.means[2, :3] = [40.0, 0.0, 3.0]     # off-screen


def run_adjoint(rt, g, cam, t, t_flow, channels=6, seed=0):
    n = len(g)
    rng = np.random.default_rng(seed)
    v = {"means2d": rng.standard_normal((n, 2)), "conic": rng.standard_normal((n, 3)),
         "opac": rng.standard_normal(n), "features": rng.standard_normal((n, channels))}
    v = {k: a.astype(np.float32) for k, a in v.items()}
    import pyopencl.array as cla
    prm = upload(rt, g)
    p = project4d(rt, prm, cam, t, t_flow, channels)
    dv = [cla.to_device(rt.queue, v[k]) for k in ("means2d", "conic", "opac", "features")]
    kg = {k[2:]: a.get() for k, a in project4d_bwd(rt, prm, cam, t, t_flow, p, *dv).items()}
    P = torch_params(g, torch.float64)
    for x in P.values():
        x.requires_grad_(True)
    r = project4d_ref(P, cam, t, t_flow, channels)
    loss = sum((r[k] * torch.from_numpy(v[k]).double()).sum() for k in v)
    if loss.requires_grad:   # False when every Gaussian is culled
        loss.backward()
    rg = {k: P[k].grad.numpy() if P[k].grad is not None else np.zeros(P[k].shape) for k in GRAD_NAMES}
    return kg, rg, r["radius"].numpy()


def assert_grads_close(kg, rg, radius):
    culled = radius <= 0
    n = len(radius)
    geo = ("means", "scales", "quat_l", "quat_r")
    # largest geometric gradient of each Gaussian: float32 round-off in one Gaussian's chain scales
    # with it (an entry that is exactly 0 by symmetry comes out as ~1e-7 of it in float32)
    geo_rows = np.max([np.abs(rg[k]).reshape(n, -1).max(1) for k in geo], 0) if n else np.zeros(0)
    for name in GRAD_NAMES:
        a, b = kg[name], rg[name]
        assert a.shape == b.shape, name
        assert np.isfinite(a).all(), name
        assert (a[culled] == 0).all() and (b[culled] == 0).all(), name
        # float32 kernel vs exact derivative: rtol 1e-3 plus an atol of 1e-4 of the largest entry of
        # the same Gaussian's gradient (cancellations inside one Gaussian's chain) and 1e-6 of the
        # largest over the scene (Gaussians near the camera have gradients 1e3 x the others).
        rows = np.abs(b).reshape(n, -1).max(1) if n else np.zeros(0)
        if name in geo:
            rows = np.maximum(rows, 1e-2 * geo_rows)
        atol = 1e-4 * rows.reshape((-1,) + (1,) * (b.ndim - 1)) + 1e-6 * (np.abs(b).max() if b.size else 0)
        assert_close(a, b, 1e-3, atol, "v_" + name)


@pytest.mark.parametrize("n,seed,t,t_flow", [(1, 0, 0.5, None), (45, 1, 0.3, 0.4), (300, 2, 0.6, 0.5),
                                             (600, 3, 0.9, 0.2)])
def test_adjoint_matches_autograd(rt, variant, n, seed, t, t_flow):
    g = Gaussians.random(small(n, 7), seed=seed)
    g.means[-1, 3] = t
    make_culled(g, t)
    kg, rg, radius = run_adjoint(rt, g, look_camera(seed), t, t_flow, seed=seed)
    assert (radius > 0).sum() >= max(1, 0.3 * len(g))
    for name in ("means", "scales", "quat_l", "quat_r", "opacity", "sh"):
        assert np.abs(rg[name][radius > 0]).max() > 0, name   # every path really carries gradient
    if t_flow is not None:
        assert np.abs(rg["phase"]).max() > 0
    assert_grads_close(kg, rg, radius)


@pytest.mark.parametrize("degree,nt,channels", [(0, 0, 3), (1, 1, 4), (3, 2, 8)])
def test_adjoint_other_sizes(rt, variant, degree, nt, channels):
    g = Gaussians.random(small(80, 5), seed=21, degree=degree, nt=nt)
    make_culled(g, 0.4)
    kg, rg, radius = run_adjoint(rt, g, look_camera(5), 0.4, 0.47, channels)
    assert_grads_close(kg, rg, radius)


def test_adjoint_flow_point_behind_camera(rt, variant):
    # a Gaussian moving along z (rotated in the (z, t) plane) whose conditional mean at t_flow is
    # behind the near plane: its flow is 0 and carries no gradient, while the rest still does.
    # (z, t) = quaternion (j, k) plane: exp(i a) on the left turns (1, i) and (j, k) by a, on the
    # right turns (1, i) by a and (j, k) by -a, so q_l = exp(i a), q_r = exp(-i a) turns (j, k) only.
    a = 0.5
    g = xt_gaussian(0.0, 0.05, 0.4, np.array([0.0, 0.0, 0.3, 0.5]))
    g.quat_l[0] = [math.cos(a), math.sin(a), 0.0, 0.0]
    g.quat_r[0] = [math.cos(a), -math.sin(a), 0.0, 0.0]
    R = rotation4d(torch.from_numpy(g.quat_l).double(), torch.from_numpy(g.quat_r).double())[0].numpy()
    np.testing.assert_allclose(R[:2, :2], np.eye(2), atol=1e-6)
    sig = covariance4d(*(torch.from_numpy(getattr(g, k)).double() for k in ("scales", "quat_l", "quat_r")))
    vz = float(sig[0, 2, 3] / sig[0, 3, 3])
    t_flow = 0.5 - math.copysign(2.0, vz)   # moves 2 |vz| towards the camera
    assert 0.3 - 2 * abs(vz) < 0.01
    cam = Camera(100.0, 100.0, 50.0, 50.0, 100, 100)
    ref = project4d_ref(torch_params(g), cam, 0.5, t_flow)
    kg, rg, radius = run_adjoint(rt, g, cam, 0.5, t_flow)
    assert radius[0] > 0
    assert (ref["features"][0, 4:] == 0).all()
    assert np.abs(rg["means"][0]).max() > 0
    assert_grads_close(kg, rg, radius)


@pytest.mark.oclgrind
def test_adjoint_tiny_oclgrind(rt, variant):
    g = Gaussians.random(7, seed=8)
    make_culled(g, 0.5)
    kg, rg, radius = run_adjoint(rt, g, look_camera(8, 48, 40), 0.5, 0.56)
    assert_grads_close(kg, rg, radius)


def test_empty_scene_adjoint(rt, variant):
    import pyopencl.array as cla
    g = Gaussians.empty()
    prm = upload(rt, g)
    cam = look_camera(0)
    p = project4d(rt, prm, cam, 0.5, None)
    z = [cla.zeros(rt.queue, s, np.float32) for s in ((0, 2), (0, 3), (0,), (0, 6))]
    grads = project4d_bwd(rt, prm, cam, 0.5, None, p, *z)
    assert grads["v_sh"].shape == (0, 3, 16, 3) and grads["v_means"].shape == (0, 4)


def test_reference_whole_stage_finite_differences():
    # the reference itself (masks, clamps, safe-where) has correct float64 derivatives
    g = Gaussians.random(4, seed=12)
    g.means[:, 3] = 0.5 + 0.1 * np.arange(4)
    g.sh[:, :, 1:, :] = 0.0   # the view direction is detached: keep the colour independent of it
    cam = look_camera(12)
    P = torch_params(g, torch.float64)
    names = ("means", "scales", "quat_l", "quat_r", "opacity", "phase")
    rng = np.random.default_rng(0)
    w = {k: torch.from_numpy(rng.standard_normal(s)) for k, s in
         (("means2d", (4, 2)), ("conic", (4, 3)), ("opac", (4,)), ("features", (4, 6)))}

    def f(*xs):
        Q = dict(P)
        Q.update(zip(names, xs))
        r = project4d_ref(Q, cam, 0.55, 0.62)
        return sum((r[k] * w[k]).sum() for k in w)

    xs = tuple(P[k].clone().requires_grad_(True) for k in names)
    assert torch.autograd.gradcheck(f, xs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_teash_colour_by_hand(rt, variant):
    # one static Gaussian straight ahead of an identity camera: view direction (0, 0, 1), where the
    # 3DGS real SH are Y_0 = C0, Y_2 = C1 z = C1, Y_6 = C2[2] (2 z^2) = 2 C2[2], Y_12 = C3[3] 2 z^3,
    # and every other basis is 0.  omega_n = 2 pi n / TEASH_PERIOD (= pi n with period 2).
    from endowave_cl.gaussians import TEASH_PERIOD
    from endowave_cl.gaussians import SH_C0, SH_C1, SH_C2, SH_C3
    g = xt_gaussian(0.0, 0.05, 0.5, np.array([0.0, 0.0, 2.0, 0.4]))
    g.sh[:] = 0.0
    g.sh[0, 0, 0] = [0.3, -0.2, -3.0]       # DC, blue clamps at 0
    g.sh[0, 0, 2] = [0.1, 0.0, 0.0]         # degree 1, z
    g.sh[0, 1, 6] = [0.0, 0.4, 0.0]         # degree 2 at frequency 1
    g.sh[0, 2, 12] = [0.0, 0.0, 0.5]        # degree 3 at frequency 2
    g.sh[0, 1, 5] = [9.0, 9.0, 9.0]         # Y_5 = C2[1] y z = 0 here: must not matter
    g.phase[0] = [5.0, 0.3, -1.1]           # phi_0 is unused
    cam = Camera(100.0, 100.0, 50.0, 50.0, 100, 100)
    t = 0.45
    p = project4d(rt, upload(rt, g), cam, t).features.get()[0, :3]
    w1, w2 = 2 * math.pi / TEASH_PERIOD, 4 * math.pi / TEASH_PERIOD
    c1, c2 = math.cos(w1 * t + 0.3), math.cos(w2 * t - 1.1)
    expect = [0.5 + SH_C0 * 0.3 + SH_C1 * 0.1,
              0.5 - SH_C0 * 0.2 + 0.4 * 2 * SH_C2[2] * c1,
              max(0.0, 0.5 - SH_C0 * 3.0 + 0.5 * 2 * SH_C3[3] * c2)]
    np.testing.assert_allclose(p, expect, rtol=1e-5, atol=1e-6)
    # a sign check of the degree-1 basis against 3DGS: Y_1 = -C1 y, Y_3 = -C1 x
    Y = sh_basis(torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64), 1).numpy()
    np.testing.assert_allclose(Y[0], [SH_C0, 0, 0, -SH_C1], atol=1e-15)
    np.testing.assert_allclose(Y[1], [SH_C0, -SH_C1, 0, 0], atol=1e-15)


def test_runaway_flow_is_dropped(rt, variant):
    # a nearly static-in-time, fast Gaussian: velocity Sigma_xt / Sigma_tt ~ 50 units per unit time,
    # ~370 px of flow over 0.15, more than the 160 x 120 image: its flow is 0 with no gradient
    # (p4_flow), while a slow one next to it keeps its flow and gradients
    cam = Camera(150.0, 160.0, 80.0, 60.0, 160, 120)
    fast = xt_gaussian(0.02, 1.0, 1e-3, np.array([0.1, -0.05, 3.0, 0.5]))
    slow = xt_gaussian(0.6, 0.05, 0.4, np.array([-0.1, 0.05, 3.0, 0.5]))
    for one in (fast, slow):
        p = project4d(rt, upload(rt, one), cam, 0.5, 0.65)
        r = project4d_ref(torch_params(one, torch.float64), cam, 0.5, 0.65, 6)
        assert p.radius.get()[0] > 0
        np.testing.assert_allclose(p.features.get()[0, 4:6], r["features"].detach().numpy()[0, 4:6],
                                   rtol=1e-4, atol=1e-3)
        kg, rg, radius = run_adjoint(rt, one, cam, 0.5, 0.65)
        assert_grads_close(kg, rg, radius)
    assert (project4d(rt, upload(rt, fast), cam, 0.5, 0.65).features.get()[0, 4:6] == 0).all()
    assert np.abs(project4d(rt, upload(rt, slow), cam, 0.5, 0.65).features.get()[0, 4:6]).max() > 1.0


# ---------------------------------------------------------------------------------------------
# the vector variant's lanes: N around multiples of the lane count, culled and special rows in
# every lane position (the rows above one at a time run the scalar kernels under a vector variant)

def special_rows(t: float) -> Gaussians:
    """The single Gaussians of the tests above and the culling cases, as one scene at time t:
    moving (x, t) Gaussians, a runaway-flow one, rows behind the camera, off-screen, outside the
    temporal window, degenerate, and at the marginal cut on both sides."""
    rows = [xt_gaussian(0.6, 0.05, 0.4, np.array([0.1, -0.05, 3.0, t])),
            xt_gaussian(0.02, 1.0, 1e-3, np.array([0.1, -0.05, 3.0, t])),      # runaway flow
            xt_gaussian(0.0, 0.05, 0.5, np.array([0.0, 0.0, 2.0, t - 0.05]))]
    g = Gaussians.random(9, seed=5, scale=0.02)
    g.means[:, 3] = t
    g.means[0, :3] = [0.0, 0.0, -2.0]                           # behind the camera
    g.means[1, :3] = [50.0, 0.0, 3.0]                           # far off-screen
    g.means[2, 3] = t + 10.0                                    # outside the temporal window
    g.scales[3] = -40.0                                         # degenerate: Sigma_tt ~ 0
    g.scales[4] = 60.0                                          # degenerate: overflows
    g.means[5, 3] = t + 2.5 * np.exp(g.scales[5, 3])            # m = 0.044 < MARGINAL_CULL: culled
    g.quat_l[5] = g.quat_r[5] = [1, 0, 0, 0]
    g.means[6, 3] = t + 2.4 * np.exp(g.scales[6, 3])            # m = 0.056: kept
    g.quat_l[6] = g.quat_r[6] = [1, 0, 0, 0]
    rows.append(g)
    return Gaussians(**{k: np.concatenate([r.as_dict()[k] for r in rows]) for k in rows[0].as_dict()})


def lane_scene(n: int, t: float, seed: int) -> Gaussians:
    """n Gaussians: the special rows repeated in a shuffled order (so that each sits in several lane
    positions, the last work-item's included) among random ones."""
    sp = special_rows(t)
    rng = np.random.default_rng(seed)
    g = Gaussians.random(n, seed=seed)
    idx = rng.permutation(n)[: min(n, 3 * len(sp))]
    for j, i in enumerate(idx):
        for k, a in g.as_dict().items():
            a[i] = sp.as_dict()[k][j % len(sp)]
    return g


@pytest.mark.parametrize("n", [3, 15, 16, 17, 31, 33, 40, 64, 71])
@pytest.mark.parametrize("t_flow", [None, 0.58])
def test_lanes_forward_and_adjoint(rt, variant, n, t_flow):
    t = 0.5
    g = lane_scene(n, t, seed=n)
    cam = Camera(150.0, 160.0, 80.0, 60.0, 160, 120)
    k, r = run_both(rt, g, cam, t, t_flow)
    if n >= 8:   # (3 rows: all visible)
        assert (r["radius"] > 0).any() and (r["radius"] == 0).any()
    assert_forward_close(k, r)
    for f in FLOAT_OUTS:
        assert (k[f][r["radius"] == 0] == 0).all(), f
    # exp(60)^2 overflows float32 (culled) but not the float64 reference of the adjoint: the forward
    # above covers it; the adjoint gets a Sigma_tt ~ 0 row instead
    g.scales[g.scales[:, 0] == 60.0] = -40.0
    kg, rg, radius = run_adjoint(rt, g, cam, t, t_flow, seed=n)
    assert_grads_close(kg, rg, radius)


@pytest.mark.oclgrind
def test_lanes_tiny_oclgrind(rt, variant):
    g = lane_scene(21, 0.5, seed=2)
    cam = Camera(150.0, 160.0, 80.0, 60.0, 160, 120)
    k, r = run_both(rt, g, cam, 0.5, 0.56)
    assert_forward_close(k, r)
    g.scales[g.scales[:, 0] == 60.0] = -40.0   # (as in test_lanes_forward_and_adjoint)
    kg, rg, radius = run_adjoint(rt, g, cam, 0.5, 0.56, seed=2)
    assert_grads_close(kg, rg, radius)


def test_variant_choice(rt, monkeypatch):
    """Devices that report a SIMT width run the scalar kernels; the others the vector ones at the
    rasterizer's lane count (or scalar where the rasterizer runs scalar); the environment forces."""
    from endowave_cl.ops.rasterize import raster_choice, simt_device
    monkeypatch.delenv(ENV_VARIANT, raising=False)
    monkeypatch.delenv(ENV_VEC_WIDTH, raising=False)
    ch = raster_choice(rt)
    expect = 0 if simt_device(rt) or ch.variant == "scalar" else ch.vw
    assert project_lanes(rt) == expect
    monkeypatch.setenv(ENV_VARIANT, "scalar")
    assert project_lanes(rt) == 0
    monkeypatch.setenv(ENV_VARIANT, "vector")
    monkeypatch.setenv(ENV_VEC_WIDTH, "8")
    assert project_lanes(rt) == 8
    monkeypatch.setenv(ENV_VEC_WIDTH, "5")
    from endowave_cl.env import EnvError
    with pytest.raises(EnvError, match=f"{ENV_VEC_WIDTH}='5'"):        # the variable named, one line
        project_lanes(rt)
