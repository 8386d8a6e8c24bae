"""Moving initialisation (train/motion.py): the 4D Gaussian of a moving point, velocities from
flow, and a short training on a scene of pure translation that ends with the right motion."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from endowave_cl.reference.project import condition_at, covariance4d, rotation4d
from endowave_cl.train.motion import (frame_velocities, linear_lifetime, gaussian_from_covariance, motion_of,
                                      moving_covariance, rotation_to_quats, spatial_size,
                                      temporal_coverage)


def test_rotation_to_quats_recovers_the_pair():
    rng = np.random.default_rng(0)
    ql, qr = rng.standard_normal((50, 4)), rng.standard_normal((50, 4))
    R = rotation4d(torch.tensor(ql), torch.tensor(qr)).numpy()
    a, b = rotation_to_quats(R)
    np.testing.assert_allclose(rotation4d(torch.tensor(a), torch.tensor(b)).numpy(), R, atol=1e-12)
    ql /= np.linalg.norm(ql, axis=1, keepdims=True)
    sign = np.sign(np.sum(a * ql, 1))[:, None]      # the pair is unique up to a common sign
    np.testing.assert_allclose(a * sign, ql, atol=1e-12)


@pytest.mark.parametrize("speed", [0.0, 0.5, 30.0])
def test_moving_gaussian_conditions_to_the_moving_point(speed):
    rng = np.random.default_rng(1)
    n = 40
    s = rng.uniform(0.01, 2.0, n)               # spatial std at any time
    st = rng.uniform(0.02, 0.5, n)              # temporal std
    v = speed * rng.standard_normal((n, 3))     # velocity, scene units per unit time
    sigma = moving_covariance(s, st, v)
    log_s, ql, qr = gaussian_from_covariance(sigma)
    cov = covariance4d(torch.tensor(log_s), torch.tensor(ql), torch.tensor(qr))
    np.testing.assert_allclose(cov.numpy(), sigma, rtol=1e-9, atol=1e-12 * np.abs(sigma).max())
    t = 0.3
    mu, cond, m = condition_at(torch.zeros(n, 4, dtype=torch.float64), cov, t)
    np.testing.assert_allclose(mu.numpy(), v * t, atol=1e-8 * max(speed, 1))
    np.testing.assert_allclose(cond.numpy(), s[:, None, None] ** 2 * np.eye(3), atol=1e-8 * max(speed, 1) ** 2)
    np.testing.assert_allclose(m.numpy(), np.exp(-0.5 * t * t / st ** 2), rtol=1e-9)
    c2, st2, v2 = motion_of(sigma)
    np.testing.assert_allclose(st2, st, rtol=1e-12)
    np.testing.assert_allclose(v2, v, atol=1e-9 * max(speed, 1))
    np.testing.assert_allclose(spatial_size(sigma), s, rtol=1e-6)
    if speed == 0:   # a still Gaussian keeps its time axis in slot 3 with identity-like rotation
        np.testing.assert_allclose(np.exp(log_s[:, 3]), st, rtol=1e-9)


class _F:  # the fields frame_velocities reads
    def __init__(self, image, depth, time, camera):
        self.image, self.depth, self.time, self.camera, self.mask = image, depth, time, camera, None


class _Pair:
    def __init__(self, src, dst, flow, valid):
        self.src, self.dst, self.flow, self.valid = src, dst, flow, valid
        self.flow_bw, self.valid_bw = -flow, valid


def _translating_plane():
    """Three frames of a plane at depth z moving at a constant image velocity, exact flow with a
    hole of failed consistency checks: (frames, pairs, z, expected world velocity [3])."""
    from endowave_cl.camera import Camera
    H, W, f, z = 20, 24, 30.0, 2.0
    cam = Camera(f, f, W / 2, H / 2, W, H)
    frames = [_F(np.zeros((H, W, 3)), np.full((H, W), z), t, cam) for t in (0.0, 0.25, 0.5)]
    flow = np.zeros((H, W, 2), np.float32)
    flow[..., 0], flow[..., 1] = 1.5, -0.5                  # px per 0.25 time
    valid = np.ones((H, W), np.float32)
    valid[5:9, 5:9] = 0                                    # filled in from the neighbours
    pairs = {0: _Pair(0, 1, flow, valid), 1: _Pair(1, 2, flow, valid)}
    return frames, pairs, z, np.array([1.5 * z / f / 0.25, -0.5 * z / f / 0.25, 0.0])


def test_frame_velocities_of_a_translating_plane():
    frames, pairs, z, want = _translating_plane()
    vel = {k: v for k, (v, _, _) in frame_velocities(frames, [0, 1, 2], pairs, depth_prior=z).items()}
    for k in (0, 1, 2):
        np.testing.assert_allclose(vel[k].reshape(-1, 3), np.broadcast_to(want, (vel[k].size // 3, 3)),
                                   rtol=1e-5, atol=1e-7)


def _translation_scene(path, W=64, H=48, frames=17, shift=(0.9, 0.4), z=2.0):
    """A textured plane at depth z translating by `shift` px per frame, static camera, with depth
    and exact flow: EndoNeRF layout."""
    import cv2
    from endowave_cl.atomic import save_png
    rng = np.random.default_rng(0)
    tex = cv2.GaussianBlur(rng.uniform(0, 1, (H + 80, W + 80, 3)).astype(np.float32), (0, 0), 2.0)
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    for sub in ("images", "depth", "gt_flow"):
        (path / sub).mkdir(parents=True)
    f = 0.8 * W
    for i in range(frames):
        M = np.float32([[1, 0, -40 + shift[0] * i], [0, 1, -40 + shift[1] * i]])   # image = tex shifted
        img = cv2.warpAffine(tex, M, (W, H), flags=cv2.INTER_LINEAR)
        save_png(path / "images" / f"{i:06d}.png", (img[..., ::-1] * 255 + 0.5).astype(np.uint8))
        save_png(path / "depth" / f"{i:06d}.png", np.full((H, W), int(z / 1e-3), np.uint16))
        np.save(path / "gt_flow" / f"{i:06d}.npy", np.broadcast_to(np.float32(shift), (H, W, 2)).copy())
    pose = np.concatenate([np.eye(3), np.zeros((3, 1)), [[H], [W], [f]]], 1)
    np.save(path / "poses_bounds.npy", np.tile(np.concatenate([pose.reshape(-1), [0.5 * z, 2 * z]]), (frames, 1)))
    (path / "scene.json").write_text(json.dumps({"depth_scale": 1e-3}))
    return shift


@pytest.mark.slow
def test_short_training_on_pure_translation_carries_the_motion(rt, tmp_path):
    """The rendered flow at the test times (never trained on) is the true translation, and the
    test frames beat the mean of their neighbouring training frames."""
    from endowave_cl.data.scene import load_scene
    from endowave_cl.metrics import psnr
    from endowave_cl.render import render
    from endowave_cl.train.config import TrainConfig
    from endowave_cl.train.trainer import Trainer
    shift = np.array(_translation_scene(tmp_path / "scene"))
    scene = load_scene(tmp_path / "scene")
    cfg = TrainConfig(iterations=200, init_points=4000, max_gaussians=16000, densify_from=50, densify_every=25,
                      densify_until=150,
                      eval_every=0, checkpoint_every=0, log_every=50, seed=0)
    tr = Trainer(scene, cfg, tmp_path / "run", rt, log=lambda s: None)
    tr.train(progress=False)
    epe, model, mean = [], [], []
    for k in scene.test_indices:
        if k + 1 >= len(scene.frames):
            continue
        fr, nxt = scene.frames[k], scene.frames[k + 1]
        out = render(rt, tr.params, fr.camera, fr.time, nxt.time).host()
        inner = (slice(6, -6), slice(6, -6))       # away from the borders the plane slides out of
        epe.append(np.linalg.norm(out["flow"][inner] - shift, axis=-1).mean())
        model.append(psnr(np.clip(out["image"], 0, 1)[inner], fr.image[inner]))
        mean.append(psnr(0.5 * (scene.frames[k - 1].image + nxt.image)[inner], fr.image[inner]))
    print(f"flow EPE {np.round(epe, 3)} px; test PSNR {np.round(model, 2)} vs neighbour mean {np.round(mean, 2)}")
    assert max(epe) < 0.3
    assert np.mean(model) > np.mean(mean) + 1.0


@pytest.mark.slow
def test_short_training_on_deforming_tissue_beats_the_neighbour_mean(rt, tmp_path):
    """Large non-rigid deformation (synthetic tissue, deformation 2, tool occluding): after a short
    training with the default method the test frames score above the mean of their neighbouring
    training frames, scored by the same evaluation as `endowave-cl eval`."""
    from endowave_cl.data.scene import load_scene
    from endowave_cl.data.synth import make_synthetic_scene
    from endowave_cl.evaluation import evaluate_run
    from endowave_cl.train.config import TrainConfig
    from endowave_cl.train.trainer import Trainer
    scene = load_scene(make_synthetic_scene(tmp_path / "scene", width=80, height=64, frames=18, seed=2,
                                            deformation=2.0))
    cfg = TrainConfig(iterations=400, densify_from=100, densify_until=300, eval_every=0, checkpoint_every=0,
                      log_every=50, seed=0)
    tr = Trainer(scene, cfg, tmp_path / "run", rt, log=lambda s: None)
    tr.train(progress=False)
    m = evaluate_run(rt, tr.params, scene, fps_runs=0, with_lpips=False, with_baselines=True)
    mean = m["baselines"]["mean"]["psnr"]
    print(f"test PSNR {m['psnr']:.2f} vs neighbour mean {mean:.2f}, flow EPE {m['flow']['model_epe']:.3f} px")
    assert m["psnr"] > mean + 0.5


def test_linear_lifetime_follows_the_curvature():
    size = np.array([0.01, 0.01, 0.01, 0.01])
    accel = np.array([0.0, 2.0, 1e6, np.nan])          # straight, curved, very curved, unknown
    t = linear_lifetime(size, accel, floor=0.03, cap=0.2)
    assert t[0] == 0.2                                  # no curvature: the cap
    assert np.isclose(t[1], np.sqrt(2 * 0.01 / 2.0))    # 0.5 |a| t^2 = size
    assert t[2] == 0.03 and t[3] == 0.03                # the floor


def test_frame_velocities_acceleration():
    """Constant velocity: zero acceleration where both estimates are trusted, unknown (NaN) where
    one is missing or failed; a speed-up between the pairs shows as its change per unit time."""
    frames, pairs, z, want = _translating_plane()
    acc = {k: a for k, (_, _, a) in frame_velocities(frames, [0, 1, 2], pairs, depth_prior=z).items()}
    assert np.isnan(acc[0]).all() and np.isnan(acc[2]).all()      # one estimate each
    assert np.isnan(acc[1][5:9, 5:9]).all()                       # consistency check failed
    known = np.isfinite(acc[1])
    assert known.sum() == acc[1].size - 16
    np.testing.assert_allclose(acc[1][known], 0.0, atol=1e-9)
    pairs[1] = _Pair(1, 2, 2 * pairs[1].flow, pairs[1].valid)      # twice as fast after frame 1
    a1 = frame_velocities(frames, [0, 1, 2], pairs, depth_prior=z)[1][2]
    np.testing.assert_allclose(a1[known], np.linalg.norm(want) / 0.25, rtol=1e-5)


def test_temporal_coverage_is_the_integral_of_the_marginal_over_the_sequence():
    mu = np.array([0.5, 0.0, 1.0, 0.3, 0.5, -0.4, 0.9])
    st = np.array([0.01, 0.05, 0.2, 0.1, 5.0, 0.1, 1e-4])
    t = np.linspace(0.0, 1.0, 200001)
    marg = np.exp(-0.5 * ((t[None, :] - mu[:, None]) / st[:, None]) ** 2)
    want = np.trapezoid(marg, t, axis=1) if hasattr(np, "trapezoid") else np.trapz(marg, t, axis=1)
    got = temporal_coverage(mu, st)
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-9)
    assert got[0] == pytest.approx(np.sqrt(2 * np.pi) * 0.01, rel=1e-9)   # well inside: sqrt(2 pi) sigma
    assert got[1] == pytest.approx(np.sqrt(2 * np.pi) * 0.05 / 2, rel=1e-9)   # centred on an end: half
    assert got[4] == pytest.approx(1.0, abs=0.01)                           # lives all along: 1
    assert got[5] < 1e-4                                                    # dead before the first frame
