"""The per-Gaussian flow loss (cl/gaussian_flow.cl) against its numpy reference
gaussian_flow_loss_ref (reference/losses.py), its place in the training step, and its effect."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pyopencl.array as cla
import pytest

from conftest import small
from endowave_cl.layout import CHANNELS, DEPTH, FLOW
from endowave_cl.loss_constants import GAUSSIAN_FLOW_DEPTH_TOL
from endowave_cl.reference.losses import gaussian_flow_loss_ref
from endowave_cl.train.config import TrainConfig
from endowave_cl.train.device_losses import PendingLosses, gaussian_flow_enqueue, prepare_targets

CH = {"depth": DEPTH, "flow": FLOW.start}


def case(seed, n, H=20, W=24):
    """Random Gaussians and images with every branch of the kernel represented: culled, centres
    outside the image and on its last row / column, untrusted flow pixels, Gaussians behind the
    surface, a pixel with zero alpha, errors on both sides of the Huber delta."""
    rng = np.random.default_rng(seed)
    means2d = np.stack([rng.uniform(-3, W + 3, n), rng.uniform(-3, H + 3, n)], 1)
    if n > 2:
        means2d[0] = (W - 0.01, H - 0.01)      # the last pixel
        means2d[1] = (W, 0.5)                  # just outside
    radius = np.where(rng.uniform(size=n) < 0.15, 0, rng.integers(1, 9, n)).astype(np.int32)
    opac = rng.uniform(0, 1, n)
    render = rng.uniform(0, 1, (H, W, CHANNELS))
    render[..., DEPTH] = rng.uniform(2, 4, (H, W))
    alpha = rng.uniform(0.5, 1, (H, W))
    alpha[3, 4] = 0.0
    surface = render[..., DEPTH] / np.where(alpha > 0, alpha, 1)
    ix = np.clip(np.floor(means2d[:, 0]), 0, W - 1).astype(int)
    iy = np.clip(np.floor(means2d[:, 1]), 0, H - 1).astype(int)
    # about a third behind the surface by more than the tolerance, the rest in front or on it
    behind = rng.uniform(size=n) < 0.3
    depth = surface[iy, ix] * np.where(behind, 1 + 3 * GAUSSIAN_FLOW_DEPTH_TOL, rng.uniform(0.8, 1.0, n))
    features = rng.normal(0, 1, (n, CHANNELS))
    features[:, FLOW] = rng.normal(0, 4, (n, 2))
    flow = rng.normal(0, 1, (H, W, 2))
    valid = (rng.uniform(size=(H, W)) > 0.25).astype(np.float32)
    f32 = lambda a: np.ascontiguousarray(a, np.float32)   # noqa: E731
    return dict(means2d=f32(means2d), opac=f32(opac), radius=radius, depth=f32(depth), features=f32(features),
                render=f32(render), alpha=f32(alpha), flow=f32(flow), valid=valid)


def run_device(rt, c, cfg):
    H, W = c["alpha"].shape
    up = lambda a: cla.to_device(rt.queue, a)   # noqa: E731
    proj = SimpleNamespace(means2d=up(c["means2d"]), opac=up(c["opac"]), radius=up(c["radius"]),
                           depth=up(c["depth"]), features=up(c["features"]))
    out = SimpleNamespace(proj=_Proj(proj), features=up(c["render"]), alpha=up(c["alpha"]), t_flow=1.0)
    tgt = prepare_targets(rt, np.zeros((H, W, 3), np.float32), None, None, c["flow"], c["valid"])
    base = PendingLosses(None, {}, lambda host: (0.0, {"total": 0.0}))
    pending = gaussian_flow_enqueue(rt, out, tgt, cfg, CH, base)
    from endowave_cl.ops.util import read_back
    host = read_back(rt, pending.sums)
    total, parts = pending.finish(host)
    return total, parts, pending.v_gaussian_features.get(), tgt.n_flow


class _Proj:
    """The Projected record's fields the loss reads, with its length."""
    def __init__(self, ns):
        self.__dict__.update(ns.__dict__)

    def __len__(self):
        return int(self.radius.shape[0])


@pytest.mark.parametrize("n", [1, 2, 63, 64, 65, 700])
@pytest.mark.parametrize("delta", [2.0, 1e9])
def test_gaussian_flow_matches_reference(rt, n, delta):
    c = case(n, n)
    cfg = TrainConfig(lambda_flow_gaussian=0.3, flow_huber_delta=delta)
    total, parts, v, n_flow = run_device(rt, c, cfg)
    coef = cfg.lambda_flow_gaussian / n_flow
    ref_sum, ref_v = gaussian_flow_loss_ref(c["means2d"], c["opac"], c["radius"], c["depth"], c["features"],
                                            c["render"], c["alpha"], c["flow"], c["valid"], coef, delta,
                                            GAUSSIAN_FLOW_DEPTH_TOL, DEPTH, FLOW.start)
    assert parts["flow_gaussian"] == pytest.approx(ref_sum / n_flow, rel=1e-5, abs=1e-9)
    assert total == pytest.approx(cfg.lambda_flow_gaussian * ref_sum / n_flow, rel=1e-5, abs=1e-9)
    np.testing.assert_allclose(v, ref_v, rtol=1e-5, atol=1e-8)
    # only the flow channels carry a gradient
    other = [k for k in range(CHANNELS) if k not in (FLOW.start, FLOW.start + 1)]
    assert not v[:, other].any()


def test_gaussian_flow_branches_are_exercised():
    """The random case reaches every branch: some Gaussians contribute, and each reason to skip one
    (culled, outside, untrusted pixel, behind the surface) occurs; both Huber sides occur."""
    c = case(700, 700)
    H, W = c["alpha"].shape
    _, v = gaussian_flow_loss_ref(c["means2d"], c["opac"], c["radius"], c["depth"], c["features"], c["render"],
                                  c["alpha"], c["flow"], c["valid"], 1.0, 2.0, GAUSSIAN_FLOW_DEPTH_TOL, DEPTH,
                                  FLOW.start)
    live = np.abs(v).sum(1) > 0
    x, y = c["means2d"][:, 0], c["means2d"][:, 1]
    inside = (x >= 0) & (y >= 0) & (x < W) & (y < H)
    ix, iy = np.clip(x.astype(int), 0, W - 1), np.clip(y.astype(int), 0, H - 1)
    surface = c["render"][iy, ix, DEPTH] / np.maximum(c["alpha"][iy, ix], 1e-9)
    assert live.sum() > 50
    assert not live[c["radius"] == 0].any() and (c["radius"] == 0).any()
    assert not live[~inside].any() and (~inside).any()
    assert not live[inside & (c["valid"][iy, ix] == 0)].any()
    behind = inside & (c["depth"] > (1 + GAUSSIAN_FLOW_DEPTH_TOL) * surface)
    assert behind.any() and not live[behind].any()
    err = np.linalg.norm(c["features"][:, FLOW] - c["flow"][iy, ix], axis=1)
    assert (live & (err > 2.0)).any() and (live & (err < 2.0)).any()


def test_gaussian_flow_no_gaussians_and_off(rt):
    c = case(0, 0)
    total, parts, v, _ = run_device(rt, c, TrainConfig(lambda_flow_gaussian=0.3))
    assert total == 0.0 and parts["flow_gaussian"] == 0.0 and v.shape[0] == 0
    c = case(5, 40)
    H, W = c["alpha"].shape
    tgt = prepare_targets(rt, np.zeros((H, W, 3), np.float32), None, None, c["flow"], c["valid"])
    base = PendingLosses(None, {}, lambda host: (0.0, {}))
    for cfg in (TrainConfig(lambda_flow_gaussian=0.0), TrainConfig(use_flow=False)):
        assert gaussian_flow_enqueue(rt, SimpleNamespace(t_flow=1.0), tgt, cfg, CH, base) is base
    no_flow = prepare_targets(rt, np.zeros((H, W, 3), np.float32))
    assert gaussian_flow_enqueue(rt, SimpleNamespace(t_flow=1.0), no_flow, TrainConfig(), CH, base) is base


@pytest.mark.oclgrind
def test_gaussian_flow_oclgrind(rt):
    n = small(130, 70)
    c = case(3, n, H=12, W=10)
    cfg = TrainConfig(lambda_flow_gaussian=0.3, flow_huber_delta=2.0)
    total, parts, v, n_flow = run_device(rt, c, cfg)
    ref_sum, ref_v = gaussian_flow_loss_ref(c["means2d"], c["opac"], c["radius"], c["depth"], c["features"],
                                            c["render"], c["alpha"], c["flow"], c["valid"],
                                            cfg.lambda_flow_gaussian / n_flow, 2.0, GAUSSIAN_FLOW_DEPTH_TOL,
                                            DEPTH, FLOW.start)
    np.testing.assert_allclose(v, ref_v, rtol=1e-5, atol=1e-8)


def test_training_step_carries_the_term(tiny_scene, rt, tmp_path):
    """In Trainer.train_step the term is summed into the total and its gradient reaches the
    parameters through project4d_bwd: the same step from the same state with the term off and on
    gives totals that differ by exactly lambda x the term, and different gradients."""
    import torch  # noqa: F401  (the trainer's reference imports stay as in training)
    from conftest import tiny_config
    from endowave_cl.data.scene import load_scene
    from endowave_cl.gaussians import download
    from endowave_cl.train.trainer import Trainer
    scene = load_scene(tiny_scene)
    runs = {}
    for lam in (0.0, 0.5):
        cfg = tiny_config(init_points=300, lambda_flow_gaussian=lam, iterations=1, densify_from=10 ** 6)
        tr = Trainer(scene, cfg, tmp_path / f"run{lam}", rt, log=lambda s: None, resume=False)
        k = next(k for k in tr.scene.train_indices if tr.targets[k].next_time is not None)
        parts = tr.train_step(k)
        runs[lam] = (parts, download(tr.params))
    off, on = runs[0.0][0], runs[0.5][0]
    assert "flow_gaussian" not in off and on["flow_gaussian"] > 0
    assert on["total"] - off["total"] == pytest.approx(0.5 * on["flow_gaussian"], rel=1e-4)
    assert on["flow"] == pytest.approx(off["flow"], rel=1e-6)
    assert not np.allclose(runs[0.0][1].quat_l, runs[0.5][1].quat_l)
