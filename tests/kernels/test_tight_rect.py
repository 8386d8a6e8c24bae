"""The tight tile rect (project4d: only the tiles where alpha can reach ALPHA_MIN) changes the work,
not the result: the image, alpha and every gradient are bit for bit those of the 3-sigma rect, with
fewer (tile, Gaussian) pairs."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import small
from endowave_cl.camera import Camera
from endowave_cl.gaussians import Gaussians, num_sh_bases, upload
from endowave_cl.ops import project as project_op
from endowave_cl.ops.project import ENV_VARIANT, ENV_VEC_WIDTH
from endowave_cl.render import render, render_backward


def _scene(n: int, width: int, height: int, seed: int) -> Gaussians:
    """Gaussians in front of an identity camera: a spread of screen sizes, elongated ones, and
    opacities from far below ALPHA_MIN (logit -8) to near 1."""
    rng = np.random.default_rng(seed)
    f = 1.1 * width
    z = rng.uniform(3.0, 5.0, n)
    u = rng.uniform(-0.1 * width, 1.1 * width, n)
    v = rng.uniform(-0.1 * height, 1.1 * height, n)
    means = np.stack([(u - width / 2) / f * z, (v - height / 2) / f * z, z, rng.uniform(0, 1, n)], 1)
    s = rng.uniform(0.5, 6.0, (n, 1)) * z[:, None] / f * np.exp(rng.uniform(-1.2, 1.2, (n, 3)))
    scales = np.log(np.concatenate([s, np.full((n, 1), 0.4)], 1))
    K = num_sh_bases(3)
    sh = np.zeros((n, 3, K, 3))
    sh[:, 0, 0, :] = rng.uniform(-1, 1, (n, 3))
    sh[:, :, 1:, :] = 0.05 * rng.standard_normal((n, 3, K - 1, 3))
    ql = np.tile([1.0, 0, 0, 0], (n, 1)) + 0.5 * rng.standard_normal((n, 4))
    qr = np.tile([1.0, 0, 0, 0], (n, 1)) + 0.05 * rng.standard_normal((n, 4))
    opacity = rng.uniform(-8.0, 4.0, n)
    return Gaussians(means, scales, ql, qr, opacity, sh, rng.uniform(-np.pi, np.pi, (n, 3)))


def _render_and_grads(rt, g, cam, seed):
    params = upload(rt, g)
    out = render(rt, params, cam, 0.45, 0.55)
    rng = np.random.default_rng(seed + 100)
    import pyopencl.array as cla
    v_feat = cla.to_device(rt.queue, rng.standard_normal((cam.height, cam.width, 6)).astype(np.float32))
    v_alpha = cla.to_device(rt.queue, rng.standard_normal((cam.height, cam.width)).astype(np.float32))
    grads = render_backward(rt, params, out, v_feat, v_alpha, deterministic=True)
    return out.n_isect, out.features.get(), out.alpha.get(), {k: v.get() for k, v in grads.items()}


@pytest.mark.parametrize("variant", ["scalar", "vector"])
@pytest.mark.parametrize("seed", [0, 1])
def test_tight_rect_same_image_and_gradients(rt, monkeypatch, variant, seed):
    monkeypatch.setenv(ENV_VARIANT, variant)
    monkeypatch.delenv(ENV_VEC_WIDTH, raising=False)
    width, height = small((120, 88), (40, 24))
    g = _scene(small(3000, 120), width, height, seed)
    cam = Camera(1.1 * width, 1.1 * width, width / 2 + 1.3, height / 2 - 0.7, width, height)
    m_tight, f_tight, a_tight, g_tight = _render_and_grads(rt, g, cam, seed)
    # the same with the 3-sigma rect (project4d.cl built with -DP4_NO_TIGHT_RECT)
    options = project_op._options
    monkeypatch.setattr(project_op, "_options", lambda *a: options(*a) + ["-DP4_NO_TIGHT_RECT"])
    m_full, f_full, a_full, g_full = _render_and_grads(rt, g, cam, seed)
    assert m_tight < m_full
    np.testing.assert_array_equal(f_tight, f_full)
    np.testing.assert_array_equal(a_tight, a_full)
    for k in g_full:
        np.testing.assert_array_equal(g_tight[k], g_full[k], err_msg=k)
