"""The in-between target's device stages (cl/between_*.cl, ops/between.py) against their references
(reference/between.py: the host path, numpy and OpenCV), with image borders, zero and wild motion,
tool masks and non-finite paths; and the whole device target against the host's between_target
(test_between.py's scenes).

Tolerance: the kernels sample where OpenCV's remap samples, with the same coefficients, but sum in
another order (and the box filter and exp differ in the last bits): every value within TOL of the
host's (images in [0, 1]), the masks' and weights' 0 / 1 decisions equal."""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import pytest

from conftest import small
from endowave_cl.ops.between import (Path, between_fuse, between_mix, between_push, between_splat, between_warp,
                                     frame_on_device, stack)
from endowave_cl.reference.between import (between_fuse_ref, between_mix_ref, between_push_ref,
                                           between_splat_ref, between_warp_ref, paths_ref)

TOL = 2e-5          # float rounding of values in [0, 1]
TRAIN_TOL = 1e-5    # the means after 12 steps with device against host targets (scene units ~1)


def _scene(h, w, seed, masks=True):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    img = [np.stack([0.5 + 0.4 * np.sin(0.3 * xx + 0.2 * yy + c + k) for c in range(3)], -1).astype(np.float32)
           for k in range(2)]
    img = [np.clip(i + 0.05 * rng.standard_normal(i.shape).astype(np.float32), 0, 1) for i in img]
    mask = [(rng.random((h, w)) > 0.1).astype(np.float32) if masks else None for _ in range(2)]
    flows = [(3.0 * rng.standard_normal((h, w, 2))).astype(np.float32) for _ in range(3)]
    return img, mask, flows


def _up(rt, a):
    return None if a is None else cla.to_device(rt.queue, np.ascontiguousarray(a, np.float32))


def _frame(rt, img, mask):
    return frame_on_device(rt, img, mask)


def _close(got, want, tol=TOL):
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got, want, rtol=0, atol=tol)


SAMPLERS = ["cubic", "lanczos"]     # the colour samplers of the warp and the push (ops/between.py)


@pytest.mark.oclgrind
@pytest.mark.parametrize("sampler", SAMPLERS)
@pytest.mark.parametrize("masks", [True, False])
def test_warp_matches_host(rt, masks, sampler):
    h, w = small((37, 53), (9, 13))
    img, mask, flows = _scene(h, w, 1, masks)
    f0, f1 = _frame(rt, img[0], mask[0]), _frame(rt, img[1], mask[1])
    A, B = _up(rt, flows[0]), _up(rt, flows[1])
    for p0, p1 in (((0.3, None), (0.7, None)), ((0.3, 0.12), (-0.4, 0.05)), ((0.0, None), (0.0, None))):
        g0 = Path(A, p0[0]) if p0[1] is None else Path(A, p0[0], B, p0[1])
        g1 = Path(B, p1[0]) if p1[1] is None else Path(B, p1[0], A, p1[1])
        hg0 = paths_ref([(p0[0], flows[0])] + ([] if p0[1] is None else [(p0[1], flows[1])]))
        hg1 = paths_ref([(p1[0], flows[1])] + ([] if p1[1] is None else [(p1[1], flows[0])]))
        blend, diff, ok = (a.get() for a in between_warp(rt, f0, f1, g0, g1, 0.75, 0.25, sampler=sampler))
        rb, rd, rok = between_warp_ref(img[0], img[1], hg0, hg1, 0.75, 0.25, mask[0], mask[1], sampler)
        _close(blend, rb)
        _close(diff, rd, tol=4 * TOL)
        np.testing.assert_array_equal(ok, rok)
        if p0[0] == 0.0:      # zero motion: the frames themselves
            np.testing.assert_allclose(blend, 0.75 * img[0] + 0.25 * img[1], atol=TOL)


@pytest.mark.oclgrind
@pytest.mark.parametrize("sampler", SAMPLERS)
def test_warp_borders_wild_and_nonfinite_paths(rt, sampler):
    h, w = small((24, 31), (8, 11))
    img, mask, _ = _scene(h, w, 2)
    g = np.zeros((h, w, 2), np.float32)
    g[0, :, 0] = 1e9          # far past the border (saturated positions, border replicated)
    g[1, :, 1] = -1e9
    g[2, :3] = np.nan         # non-finite: remap samples the first (bicubic) or last (Lanczos) pixel
    g[3, :3, 0] = np.inf
    g[3, 3:6, 1] = -np.inf
    # offsets at odd multiples of 1/64 px: Lanczos-4 rounds positions to 1/32 px, half to even
    g[4, :, 0] = (np.arange(w) - w // 2) * np.float32(1.0 / 64.0) * 3
    g[5:, :] = np.random.default_rng(0).uniform(-2 * w, 2 * w, (h - 5, w, 2))
    f0, f1 = _frame(rt, img[0], mask[0]), _frame(rt, img[1], mask[1])
    G = _up(rt, g)
    blend, diff, ok = (a.get() for a in between_warp(rt, f0, f1, Path(G, 1.0), Path(G, -0.5), 0.5, 0.5,
                                                      sampler=sampler))
    rb, rd, rok = between_warp_ref(img[0], img[1], g, -0.5 * g, 0.5, 0.5, mask[0], mask[1], sampler)
    _close(blend, rb)
    np.testing.assert_array_equal(ok, rok)


@pytest.mark.oclgrind
@pytest.mark.parametrize("mode", ["agree", "mean"])
def test_fuse_matches_host(rt, mode):
    h, w = small((29, 41), (9, 12))
    rng = np.random.default_rng(3)
    K = 3
    blend = rng.random((K, h, w, 3)).astype(np.float32)
    diff = (0.05 * rng.random((K, h, w))).astype(np.float32)
    ok = (rng.random((K, h, w)) > 0.3).astype(np.float32)
    ok[:, 0, 0] = 0           # no hypothesis usable: all fused, weight 0
    image, weight = between_fuse(rt, _up(rt, blend), _up(rt, diff), _up(rt, ok), 3, 0.02, mode)
    ri, rw = between_fuse_ref(blend, diff, ok, 3, 0.02, mode)
    _close(image.get(), ri)
    np.testing.assert_array_equal(weight.get(), rw)
    assert weight.get()[0, 0] == 0


@pytest.mark.oclgrind
def test_fuse_one_hypothesis_is_that_hypothesis(rt):
    h, w = small((12, 17), (5, 6))
    blend = np.random.default_rng(4).random((1, h, w, 3)).astype(np.float32)
    ok = np.ones((1, h, w), np.float32)
    ok[0, 1, 1] = 0
    image, weight = between_fuse(rt, _up(rt, blend), _up(rt, np.zeros((1, h, w))), _up(rt, ok), 3, 0.02)
    np.testing.assert_array_equal(image.get(), blend[0])
    np.testing.assert_array_equal(weight.get(), ok[0])


@pytest.mark.oclgrind
@pytest.mark.parametrize("masks", [True, False])
def test_splat_matches_host(rt, masks):
    h, w = small((33, 47), (8, 10))
    img, mask, flows = _scene(h, w, 5, masks)
    g = flows[0].copy()
    g[0, 0] = (-0.5, -0.5)       # lands across the top-left border
    g[-1, -1] = (0.7, 0.2)       # across the bottom-right one
    g[1, 1] = np.nan             # reaches nothing
    g[2, 2] = (1e12, 0)          # far outside
    f = _frame(rt, img[0], mask[0])
    acc = between_splat(rt, Path(_up(rt, g), 1.0), f).get()
    den, num = between_splat_ref(g, mask[0])
    unit = 2.0 ** -32
    np.testing.assert_allclose(acc[..., 0] * unit, den, atol=1e-6)
    np.testing.assert_allclose(acc[..., 1:] * unit, num, atol=1e-5, rtol=1e-6)
    # zero motion: each pixel lands on itself with weight 1 (0 on tool pixels)
    z = between_splat(rt, Path(_up(rt, np.zeros((h, w, 2))), 1.0), f).get()
    np.testing.assert_array_equal(z[..., 0] * unit, 1.0 if mask[0] is None else mask[0])
    assert not z[..., 1:].any()


def test_splat_is_deterministic(rt):
    h, w = small((64, 80), (8, 8))
    g = np.random.default_rng(6).normal(0, 0.3, (h, w, 2)).astype(np.float32)   # many pixels meet
    G, f = _up(rt, g), _frame(rt, np.zeros((h, w, 3), np.float32), None)
    runs = [between_splat(rt, Path(G, 1.0), f).get() for _ in range(3)]
    for r in runs[1:]:
        np.testing.assert_array_equal(r, runs[0])


@pytest.mark.oclgrind
@pytest.mark.parametrize("sampler", SAMPLERS)
def test_push_matches_host(rt, sampler):
    h, w = small((31, 43), (9, 11))
    img, mask, flows = _scene(h, w, 7)
    g0, g1 = 0.4 * flows[0], -0.6 * flows[1]
    g1[:, : w // 3] = 50.0       # the second frame reaches nothing there: the first alone, or fill
    fill = np.full((h, w, 3), 0.25, np.float32)
    f0, f1 = _frame(rt, img[0], mask[0]), _frame(rt, img[1], mask[1])
    a0 = between_splat(rt, Path(_up(rt, g0), 1.0), f0)
    a1 = between_splat(rt, Path(_up(rt, g1), 1.0), f1)
    got = between_push(rt, a0, a1, f0, f1, 0.6, 0.4, _up(rt, fill), 0.05, sampler).get()
    want = between_push_ref(img[0], img[1], between_splat_ref(g0, mask[0]), between_splat_ref(g1, mask[1]),
                            0.6, 0.4, fill, 0.05, sampler)
    _close(got, want)
    assert (got == 0.25).all(-1).any()      # some pixels reached by neither keep the fill


@pytest.mark.oclgrind
def test_mix_and_count(rt):
    h, w = small((19, 23), (6, 7))
    rng = np.random.default_rng(8)
    flow, model = rng.random((2, h, w, 3)).astype(np.float32)
    weight = (rng.random((h, w)) > 0.2).astype(np.float32)
    ok = (rng.random((h, w)) > 0.2).astype(np.float32)
    for m, mw, o in ((model, 0.5, ok), (None, 0.0, None), (model, 0.3, None)):
        image, wt, count = between_mix(rt, _up(rt, flow), _up(rt, weight), _up(rt, m), mw, _up(rt, o))
        ri, rw, rc = between_mix_ref(flow, weight, m, mw, o)
        np.testing.assert_array_equal(image.get(), ri)
        np.testing.assert_array_equal(wt.get(), rw)
        assert int(count.get()[0]) == rc


def test_unknown_sampler_is_refused(rt):
    img, mask, flows = _scene(5, 6, 3)
    f0 = _frame(rt, img[0], mask[0])
    with pytest.raises(ValueError, match="sampler must be one of cubic, lanczos"):
        between_warp(rt, f0, f0, Path(_up(rt, flows[0]), 0.5), Path(_up(rt, flows[1]), 0.5), 0.5, 0.5,
                     sampler="nearest")


def test_stack(rt):
    a = [np.full((3, 4), i, np.float32) for i in range(3)]
    np.testing.assert_array_equal(stack(rt, [_up(rt, x) for x in a]).get(), np.stack(a))


# ------------------------------------------------------------------ the whole target, device against host
def _sampler(rt, scene, monkeypatch, **kw):
    from endowave_cl.train.between import BetweenSampler, between_flows
    from conftest import tiny_config
    monkeypatch.setenv("ENDOWAVE_BETWEEN_TARGET", "device")
    cfg = tiny_config(**{"between_levels": 0, **kw})   # the host's exact target at any s (not kept in float16)
    flows, extra = between_flows(scene, cfg)
    b = BetweenSampler.from_config(rt, scene, cfg, flows, extra)
    assert b.device is not None
    return b


def _compare_targets(b, draws, seed):
    """The device target (DeviceTarget.build) against the host's (BetweenSampler.target) for draws
    (pair index, s), without and with the model's motion (random, as a render's would be)."""
    rng = np.random.default_rng(seed)
    h, w = b.scene.height, b.scene.width
    for index, s in draws:
        disp, g0, g1 = (rng.normal(0, 1.5, (h, w, 2)).astype(np.float32) for _ in range(3))
        for model in (False, True):
            fwd = ((g0, np.float32(s)), (g1, np.float32(1 - s))) if model else None
            args = (disp, 0.5) if model else (None, 0.0)
            image, weight, count = b.device.build(index, s, *args, fwd)
            want, want_w, _ = b.target(index, s, *args, None if fwd is None else (fwd[0][1] * g0, fwd[1][1] * g1))
            _close(image.get(), want)
            np.testing.assert_array_equal(weight.get(), want_w)
            assert int(count.get()[0]) == int((want_w > 0).sum())


@pytest.mark.parametrize("settings", [{}, dict(between_path="linear", between_fuse="mean"),
                                      dict(between_flow_splat=False),
                                      dict(between_flows="")])
def test_device_target_matches_host_target(rt, tiny_scene, monkeypatch, settings):
    from endowave_cl.data.scene import load_scene
    b = _sampler(rt, load_scene(tiny_scene), monkeypatch, **settings)
    n = len(b.pairs)
    _compare_targets(b, [(0, 0.5), (n - 1, 0.13), (n // 2, 0.9)], 0)


def test_device_target_matches_host_target_with_lanczos(rt, tiny_scene, monkeypatch):
    """train/between.py SAMPLER reaches the device target's every warp and push."""
    import endowave_cl.train.between as between
    from endowave_cl.data.scene import load_scene
    monkeypatch.setattr(between, "SAMPLER", "lanczos")
    b = _sampler(rt, load_scene(tiny_scene), monkeypatch)
    assert b.device.colour == "lanczos"
    _compare_targets(b, [(0, 0.5), (len(b.pairs) - 1, 0.13)], 2)


def test_device_target_matches_host_target_on_pulling(rt, pulling_scene, monkeypatch):
    """The default settings on the real frames (three estimators, tool masks, curved paths)."""
    from endowave_cl.data.scene import load_scene
    b = _sampler(rt, load_scene(pulling_scene, downscale=4), monkeypatch)
    _compare_targets(b, [(0, 0.41), (len(b.pairs) - 1, 0.77), (17, 0.05)], 1)


def test_where_the_targets_are_built(rt, monkeypatch):
    """auto: on a GPU only; 'host' always on the host; a bad value is the one-line EnvError."""
    from endowave_cl.env import EnvError
    from endowave_cl.train.between import targets_on_device
    monkeypatch.setenv("ENDOWAVE_BETWEEN_TARGET", "auto")
    assert targets_on_device(rt) == rt.is_gpu
    monkeypatch.setenv("ENDOWAVE_BETWEEN_TARGET", "host")
    assert not targets_on_device(rt)
    monkeypatch.setenv("ENDOWAVE_BETWEEN_TARGET", "gpu")
    with pytest.raises(EnvError, match="ENDOWAVE_BETWEEN_TARGET"):
        targets_on_device(rt)


def test_training_with_device_targets(rt, tiny_scene, tmp_path, monkeypatch):
    """A short training whose in-between steps (before and after densify_until: the model's motion
    blended in) take their targets from the device: the same result twice (the splats' integer sums
    are order-free), and within TRAIN_TOL of the host-built targets' run over 12 steps (the targets
    differ by float rounding only)."""
    from endowave_cl.data.scene import load_scene
    from endowave_cl.gaussians import download
    from endowave_cl.train.trainer import Trainer
    from conftest import tiny_config
    scene = load_scene(tiny_scene)
    out = {}
    for name, where in (("device", "device"), ("again", "device"), ("host", "host")):
        monkeypatch.setenv("ENDOWAVE_BETWEEN_TARGET", where)
        tr = Trainer(scene, tiny_config(iterations=12, init_points=1500, between_prob=1.0, densify_from=1000,
                                        densify_until=6, between_motion_refresh=4, deterministic=True,
                                        between_levels=0),   # host targets exact, not kept in float16
                     tmp_path / name, rt, log=lambda s: None)
        assert (tr._between.device is not None) == (where == "device")
        tr.train(progress=False)
        out[name] = download(tr.params).means
    np.testing.assert_array_equal(out["device"], out["again"])
    np.testing.assert_allclose(out["device"], out["host"], rtol=0, atol=TRAIN_TOL)


def test_device_targets_that_supervise_nothing_drop_their_step(rt, tiny_scene, tmp_path, monkeypatch):
    """The supervised pixel count of a device-built target stays on the device; a step whose
    target supervises nothing is dropped after its read-back, nothing changed, and the schedule
    takes a plain step instead: the same run, bit for bit, as reading the count in the draw and
    skipping the step there (what the sampler did before)."""
    from endowave_cl.data.scene import load_scene
    from endowave_cl.gaussians import PARAM_NAMES, download
    from endowave_cl.train import between as between_mod
    from endowave_cl.train.between_device import DeviceTarget
    from endowave_cl.train.trainer import Trainer
    from conftest import tiny_config
    scene = load_scene(tiny_scene)
    monkeypatch.setenv("ENDOWAVE_BETWEEN_TARGET", "device")
    build, draw = DeviceTarget.build, between_mod.BetweenSampler.draw

    builds = []

    def every_other_empty(self, *a, **kw):
        image, weight, count = build(self, *a, **kw)
        builds.append(1)
        if len(builds) % 2:
            weight.fill(np.float32(0))
            count.fill(np.int32(0))
        return image, weight, count

    def draw_reading_the_count(self, *a, **kw):
        drawn = draw(self, *a, **kw)
        if drawn is not None and int(drawn[2].supervised.get()[0]) == 0:
            return None
        return drawn
    monkeypatch.setattr(DeviceTarget, "build", every_other_empty)
    runs = {}
    for name in ("on_device", "read_in_draw"):
        if name == "read_in_draw":
            monkeypatch.setattr(between_mod.BetweenSampler, "draw", draw_reading_the_count)
        tr = Trainer(scene, tiny_config(iterations=10, init_points=1500, between_prob=0.7, densify_from=1000,
                                        densify_until=5, between_motion_refresh=3, deterministic=True),
                     tmp_path / name, rt, log=lambda s: None)
        kinds = []
        builds.clear()
        order = list(scene.train_indices)
        for _ in range(10):
            kinds.append(tr.schedule_step(order)[0])
        runs[name] = (kinds, download(tr.params), tr.step)
        assert len(builds) > kinds.count("between")          # some targets supervised nothing
    (k0, g0, s0), (k1, g1, s1) = runs["on_device"], runs["read_in_draw"]
    assert k0 == k1 and s0 == s1 == 10 and "between" in k0
    assert sum(1 for k in k0 if k == "plain") > 0
    for name in PARAM_NAMES:
        assert np.array_equal(getattr(g0, name), getattr(g1, name)), name
