"""Supervision between training frames (train/between.py): the predicted frame against an exact
translation, the trust mask, the camera rule, and a trainer step at an in-between time."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from conftest import tiny_config


def _textured(H=40, W=56, seed=0):
    import cv2
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.uniform(0, 1, (H + 40, W + 40, 3)).astype(np.float32), (0, 0), 2.5)
    return (tex - tex.min()) / (tex.max() - tex.min())


def _shifted(tex, dx, dy, H, W):
    """tex moved by (dx, dy), sampled bicubically as the in-between target samples (whole-pixel
    shifts are exact)."""
    import cv2
    M = np.float32([[1, 0, -20 + dx], [0, 1, -20 + dy]])
    return cv2.warpAffine(tex, M, (W, H), flags=cv2.INTER_CUBIC)


def _scene_and_pair(shift=(2.0, -1.0), H=40, W=56, mask=None):
    from endowave_cl.camera import Camera
    from endowave_cl.data.flow import FlowPair
    from endowave_cl.data.scene import Frame, Scene
    tex = _textured(H, W)
    cam = Camera(width=W, height=H, fx=50.0, fy=50.0, cx=W / 2, cy=H / 2, viewmat=np.eye(4, dtype=np.float32))
    frames = [Frame(i, i / 2, _shifted(tex, shift[0] * i, shift[1] * i, H, W), None, mask, cam) for i in range(3)]
    scene = Scene(path=None, frames=frames, train_indices=[0, 2], test_indices=[1], near=0.1, far=10.0,
                  width=W, height=H, has_depth=False, has_masks=mask is not None)
    fw = np.broadcast_to(np.float32([2 * shift[0], 2 * shift[1]]), (H, W, 2)).copy()
    ones = np.ones((H, W), np.float32)
    return scene, FlowPair(0, 2, fw, ones.copy(), -fw, ones.copy()), tex


def test_between_target_is_the_translated_frame():
    from endowave_cl.train.between import between_target
    scene, pair, tex = _scene_and_pair()
    image, weight, t = between_target(scene, pair, 0.5)
    assert t == pytest.approx(0.5)
    inner = (slice(6, -6), slice(6, -6))        # away from the borders the warp repeats
    np.testing.assert_allclose(image[inner], scene.frames[1].image[inner], atol=2e-3)
    assert weight.min() == 1.0
    # a quarter of the way: the texture moved a quarter of the pair's displacement
    image, _, t = between_target(scene, pair, 0.25)
    assert t == pytest.approx(0.25)
    want = _shifted(tex, 0.5 * 2.0, 0.5 * -1.0, *image.shape[:2])
    frame = scene.frames[0].image                  # the target clips bicubic overshoot to the frames' range
    np.testing.assert_allclose(image[inner], np.clip(want, frame.min(), frame.max())[inner], atol=2e-3)


def test_between_target_supervises_tissue_only():
    from endowave_cl.train.between import between_target
    H, W = 40, 56
    mask = np.ones((H, W), np.float32)
    mask[:, :10] = 0.0                                   # a tool along the left border
    scene, pair, _ = _scene_and_pair(shift=(4.0, 0.0), mask=mask)
    pair.valid[5:9, 20:30] = 0.0                         # a failed consistency check is still supervised
    _, weight, _ = between_target(scene, pair, 0.5)
    # frame 0 is warped by 0.5 * 8 px, frame 2 by -0.5 * -8 px: the tool's columns move with it
    assert weight[:, :14].max() == 0.0
    assert weight[:, 16:].min() == 1.0


def test_two_flow_displacements():
    from endowave_cl.baselines import two_flow_displacements
    rng = np.random.default_rng(2)
    f01 = rng.normal(0, 3, (5, 7, 2)).astype(np.float32)
    # consistent flows (f10 = -f01): each frame's own flow, scaled to the time fraction
    for t in (0.25, 0.5, 0.8):
        d0, d1 = two_flow_displacements(f01, -f01, t)
        np.testing.assert_allclose(d0, -t * f01, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(d1, (1 - t) * f01, rtol=1e-6, atol=1e-6)
    # inconsistent ones: at t = 1/4 frame 0's estimate of the motion weighs 3 to 1
    f10 = rng.normal(0, 3, (5, 7, 2)).astype(np.float32)
    d0, d1 = two_flow_displacements(f01, f10, 0.25)
    motion = 0.75 * f01 - 0.25 * f10                 # the pair's displacement, both flows averaged
    np.testing.assert_allclose(d0, -0.25 * motion, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(d1, 0.75 * motion, rtol=1e-5, atol=1e-6)




def test_pairs_with_a_moving_camera_are_not_used():
    from endowave_cl.train.between import usable_pairs
    scene, pair, _ = _scene_and_pair()
    assert usable_pairs(scene, {0: pair}) == [pair]
    moved = np.eye(4, dtype=np.float32)
    moved[0, 3] = 0.1
    scene.frames[2] = dataclasses.replace(scene.frames[2],
                                          camera=dataclasses.replace(scene.frames[2].camera, viewmat=moved))
    assert usable_pairs(scene, {0: pair}) == []


@pytest.mark.slow
def test_trainer_steps_between_frames(rt, tiny_scene, tmp_path):
    """between_prob = 1: every step renders at an in-between time; the parameters change and the
    loop still logs from its training frames."""
    from endowave_cl.data.scene import load_scene
    from endowave_cl.gaussians import download
    from endowave_cl.train.trainer import Trainer
    scene = load_scene(tiny_scene)
    tr = Trainer(scene, tiny_config(iterations=6, init_points=2000, between_prob=1.0, densify_from=1000,
                                    log_every=1), tmp_path / "run", rt, log=lambda s: None)
    assert tr._between
    before = download(tr.params).sh.copy()
    times = []
    real_step = tr._step
    tr._step = lambda cam, t, t_next, dev, what, **kw: (times.append(t), real_step(cam, t, t_next, dev, what, **kw))[1]
    tr.train(progress=False)
    train_times = {scene.frames[k].time for k in scene.train_indices}
    assert len(times) == 6 and not any(t in train_times for t in times)
    assert not np.array_equal(download(tr.params).sh, before)


def test_sample_displaced_samplers():
    from endowave_cl.baselines import sample_displaced
    H, W, P = 24, 64, 5.0                                  # a sinusoid of 5 px period along x
    x = np.arange(W, dtype=np.float32)
    img = np.broadcast_to(0.5 + 0.4 * np.sin(2 * np.pi * x / P), (H, W)).astype(np.float32).copy()
    inner = (slice(None), slice(4, -4))
    for shift in (1.0, -2.0):                              # whole pixels: both are the shifted image
        disp = np.zeros((H, W, 2), np.float32)
        disp[..., 0] = shift
        want = 0.5 + 0.4 * np.sin(2 * np.pi * (x + shift) / P)
        for sampler in ("linear", "cubic"):
            np.testing.assert_allclose(sample_displaced(img, disp, sampler)[inner], np.broadcast_to(want, (H, W))[inner],
                                       atol=1e-5)
    disp = np.zeros((H, W, 2), np.float32)
    disp[..., 0] = 0.5                                     # half a pixel: bilinear averages two samples
    want = np.broadcast_to(0.5 + 0.4 * np.sin(2 * np.pi * (x + 0.5) / P), (H, W))
    err = {s: np.abs(sample_displaced(img, disp, s) - want)[inner].max() for s in ("linear", "cubic")}
    # bilinear shrinks the sinusoid by cos(pi / P) (about 0.08 of its 0.4 amplitude); bicubic keeps it
    assert err["linear"] > 0.06 and err["cubic"] < 0.03, err
    # a step edge: the cubic kernel's overshoot is clipped to the image's range
    step = np.zeros((H, W), np.float32)
    step[:, W // 2:] = 1.0
    disp[..., 0] = 0.3
    out = sample_displaced(step, disp, "cubic")
    assert out.min() >= 0.0 and out.max() <= 1.0
    with pytest.raises(ValueError, match="sampler"):
        sample_displaced(img, disp, "nearest")


def test_between_target_sampler():
    # the texture moves 1 px per frame: half-way both warps are whole pixels and give the middle
    # frame; a quarter of the way (half a pixel) the frames are sampled bicubically
    from endowave_cl.baselines import sample_displaced
    from endowave_cl.train.between import between_target
    scene, pair, _ = _scene_and_pair(shift=(1.0, 0.0))
    inner = (slice(6, -6), slice(6, -6))
    cub, _, _ = between_target(scene, pair, 0.5)
    np.testing.assert_allclose(cub[inner], scene.frames[1].image[inner], atol=1e-5)
    cub, _, _ = between_target(scene, pair, 0.25)
    i0, i1 = scene.frames[0].image, scene.frames[2].image
    want = 0.75 * sample_displaced(i0, -0.25 * pair.flow, "cubic") + 0.25 * sample_displaced(i1, -0.75 * pair.flow_bw, "cubic")
    np.testing.assert_allclose(cub, want, atol=1e-6)


def _fused_ref(warps, s, valid, radius, tau):
    """fused_interpolation computed pixel by pixel (box mean with the border reflected as
    cv2.blur's default, BORDER_REFLECT_101 = numpy's "reflect")."""
    K = len(warps)
    H, W = warps[0][0].shape[:2]
    err = np.zeros((K, H, W))
    for k, (w0, w1) in enumerate(warps):
        d = np.pad(np.abs(w0.astype(np.float64) - w1).sum(-1), radius, mode="reflect")
        for y in range(H):
            for x in range(W):
                err[k, y, x] = d[y:y + 2 * radius + 1, x:x + 2 * radius + 1].mean()
    image = np.zeros((H, W, 3))
    weight = np.zeros((H, W))
    for y in range(H):
        for x in range(W):
            use = [k for k in range(K) if valid[k][y, x] > 0] or list(range(K))
            weight[y, x] = float(any(valid[k][y, x] > 0 for k in range(K)))
            best = min(err[k, y, x] for k in use)
            ws = {k: np.exp(-(err[k, y, x] - best) / tau) for k in use}
            total = sum(ws.values())
            for k, wk in ws.items():
                image[y, x] += wk / total * ((1 - s) * warps[k][0][y, x] + s * warps[k][1][y, x])
    return image, weight


def test_fused_interpolation_against_reference():
    from endowave_cl.train.between import FUSE_RADIUS, FUSE_TAU, fused_interpolation
    rng = np.random.default_rng(5)
    H, W, K, s = 12, 15, 3, 0.3
    base = rng.uniform(0, 1, (H, W, 3)).astype(np.float32)
    # hypotheses whose two warps disagree by different amounts in different places
    warps = [(base, np.clip(base + rng.normal(0, sd, (H, W, 3)), 0, 1).astype(np.float32))
             for sd in (0.01, 0.03, 0.1)]
    valid = [np.ones((H, W), np.float32) for _ in range(K)]
    valid[0][:4] = 0.0                      # the best hypothesis unusable in the top rows
    for v in valid:
        v[5, 7] = 0.0                       # and no hypothesis at one pixel
    image, weight = fused_interpolation(warps, s, valid)
    ref_image, ref_weight = _fused_ref(warps, s, valid, FUSE_RADIUS, FUSE_TAU)
    np.testing.assert_allclose(image, ref_image, atol=1e-5)
    np.testing.assert_array_equal(weight, ref_weight)
    assert weight[5, 7] == 0.0 and weight.sum() == H * W - 1


def test_fused_interpolation_mean_against_reference():
    """mode "mean": every valid hypothesis has the same weight (the reference with an infinite
    tau); where none is valid, all of them, with weight 0."""
    from endowave_cl.train.between import fused_interpolation
    rng = np.random.default_rng(6)
    H, W, s = 10, 13, 0.7
    warps = [tuple(rng.uniform(0, 1, (H, W, 3)).astype(np.float32) for _ in range(2)) for _ in range(3)]
    valid = [np.ones((H, W), np.float32) for _ in range(3)]
    valid[1][:, :5] = 0.0
    for v in valid:
        v[2, 3] = 0.0
    image, weight = fused_interpolation(warps, s, valid, "mean")
    ref_image, ref_weight = _fused_ref(warps, s, valid, 1, np.inf)
    np.testing.assert_allclose(image, ref_image, atol=1e-5)
    np.testing.assert_array_equal(weight, ref_weight)
    plain = sum((1 - s) * w0 + s * w1 for w0, w1 in warps) / 3
    np.testing.assert_allclose(image[:, 5:][weight[:, 5:] > 0], plain[:, 5:][weight[:, 5:] > 0], atol=1e-5)


def test_fused_interpolation_prefers_the_hypothesis_whose_warps_agree():
    # two hypotheses of a frame half-way between two frames of a translating texture: the right
    # flow and a flow that is 3 px off.  Fused, the result is the right one's almost everywhere;
    # two copies of one hypothesis fuse to that hypothesis exactly.
    from endowave_cl.data.flow import FlowPair
    from endowave_cl.train.between import between_target
    scene, pair, _ = _scene_and_pair(shift=(2.0, -1.0), H=48, W=64)
    wrong = FlowPair(0, 2, pair.flow + np.float32([3.0, 0.0]), pair.valid, pair.flow_bw - np.float32([3.0, 0.0]), pair.valid_bw)
    inner = (slice(8, -8), slice(8, -8))
    right, _, _ = between_target(scene, pair, 0.5)
    bad, _, _ = between_target(scene, wrong, 0.5)
    fused, weight, _ = between_target(scene, wrong, 0.5, extra=[pair])
    truth = scene.frames[1].image
    err = lambda im: np.abs(im - truth)[inner].mean()
    assert err(bad) > 5 * err(right)
    assert err(fused) < 1.5 * err(right) + 1e-4
    twice, w2, _ = between_target(scene, pair, 0.5, extra=[pair])
    np.testing.assert_allclose(twice, right, atol=1e-6)
    assert weight.min() == 1.0 and w2.min() == 1.0


def test_between_target_blends_the_models_motion():
    """model_disp: the pair's frames warped along the model's displacement to the first frame (and
    the same motion scaled to the second) are blended in with model_weight.  Exact motion gives the
    translated frame; a still model gives the two frames' mean; weight 0 leaves the flow's target."""
    from endowave_cl.baselines import mean_interpolation
    from endowave_cl.train.between import between_target
    scene, pair, _ = _scene_and_pair()
    H, W = scene.height, scene.width
    inner = (slice(6, -6), slice(6, -6))
    flow_only, w0, t0 = between_target(scene, pair, 0.25)
    # the texture moves by (4, -2) px from frame 0 to frame 2: at s = 0.25 a pixel of the frame at
    # s lies at p - 0.25 * (4, -2) in frame 0
    exact = np.broadcast_to(np.float32([-1.0, 0.5]), (H, W, 2)).copy()
    for weight in (0.5, 1.0):
        image, w, t = between_target(scene, pair, 0.25, model_disp=exact, model_weight=weight)
        assert t == t0
        np.testing.assert_array_equal(w, w0)
        np.testing.assert_allclose(image[inner], flow_only[inner], atol=2e-3)
    still = np.zeros((H, W, 2), np.float32)
    image, _, _ = between_target(scene, pair, 0.25, model_disp=still, model_weight=1.0)
    np.testing.assert_allclose(image, mean_interpolation(scene.frames[0].image, scene.frames[2].image, 0.25),
                               atol=1e-6)
    half, _, _ = between_target(scene, pair, 0.25, model_disp=still, model_weight=0.5)
    np.testing.assert_allclose(half, 0.5 * flow_only + 0.5 * image, atol=1e-6)
    same, _, _ = between_target(scene, pair, 0.25, model_disp=still, model_weight=0.0)
    np.testing.assert_array_equal(same, flow_only)
    at_first, _, _ = between_target(scene, pair, 0.0, model_disp=exact, model_weight=0.5)
    assert np.isfinite(at_first).all()                   # s = 0: no division by zero


def test_trainer_blends_the_models_motion_after_densification(rt, tiny_scene, tmp_path):
    """between_model > 0: from densify_until on, each in-between step's forward renders the flow to
    the pair's first frame and the target is made from it; before, and with weight 0, never.  (The
    pair's motion rendered to the step's time each step: between_motion_refresh 0; kept per pair:
    test_config_keys.)"""
    from endowave_cl.data.scene import load_scene
    from endowave_cl.train.trainer import Trainer
    scene = load_scene(tiny_scene)
    train_times = {scene.frames[k].time for k in scene.train_indices}
    for weight, start, want, splat in ((0.5, 3, 3, False), (0.5, 3, 3, True), (0.0, 0, 0, True)):
        tr = Trainer(scene, tiny_config(iterations=6, init_points=2000, between_prob=1.0, densify_from=1000,
                                        densify_until=start, between_model=weight, log_every=1,
                                        between_model_splat=splat, between_motion_refresh=0),
                     tmp_path / f"run{weight}{splat}", rt, log=lambda s: None)
        calls, forwards = [], []
        real_motion, real_step = tr.rendered_motion, tr._step

        def spy(out):
            disp = real_motion(out)
            if not out.overflowed:   # a render whose pairs overflowed the binning's buffers is rendered again
                calls.append((tr.step, out.t, out.t_flow, disp.shape))
            return disp
        tr.rendered_motion = spy
        tr._step = lambda cam, t, t_next, dev, what, out=None: (forwards.append(out), real_step(cam, t, t_next, dev, what, out))[1]
        tr.train(progress=False)
        per_step = 3 if splat else 1     # with the splat, two more renders at the pair's frames
        assert len(calls) == want * per_step
        for i in range(0, len(calls), per_step):
            step, t, t_to, shape = calls[i]
            assert step >= start and t_to in train_times and t > t_to
            assert shape == (scene.height, scene.width, 2)
            if splat:   # the pair's first frame to t, then its second frame to t
                (_, ta, ta_to, _), (_, tb, tb_to, _) = calls[i + 1], calls[i + 2]
                assert ta == t_to and ta_to == t and tb in train_times and tb > t and tb_to == t
        # the render that gave the motion at t is the step's own forward: no second render of it
        assert sum(f is not None for f in forwards) == want
        assert all(f is None or f.t not in train_times for f in forwards)


def test_between_target_with_the_models_motion_supervises_tissue_only():
    """With tool masks, a pixel is supervised only where the model's warps show tissue too."""
    from endowave_cl.train.between import between_target
    H, W = 40, 56
    mask = np.ones((H, W), np.float32)
    mask[:, :10] = 0.0                                   # a tool along the left border
    scene, pair, _ = _scene_and_pair(shift=(4.0, 0.0), mask=mask)
    _, flow_weight, _ = between_target(scene, pair, 0.5)
    # the model says the tissue at p was at p - (6, 0) in frame 0, so it will be at p + (6, 0) in frame 2
    disp = np.broadcast_to(np.float32([-6.0, 0.0]), (H, W, 2)).copy()
    _, weight, _ = between_target(scene, pair, 0.5, model_disp=disp, model_weight=0.5)
    assert weight[:, :16].max() == 0.0                   # frame 0's tool seen through p - 6
    assert weight[:, 17:].min() == 1.0
    assert (weight <= flow_weight).all()


def _splat_ref(image, disp, weight=None):
    """splat_forward pixel by pixel."""
    H, W = disp.shape[:2]
    num = np.zeros((H, W, image.shape[-1]))
    den = np.zeros((H, W))
    for y in range(H):
        for x in range(W):
            px, py = x + float(disp[y, x, 0]), y + float(disp[y, x, 1])
            if not (np.isfinite(px) and np.isfinite(py)):
                continue
            x0, y0 = int(np.floor(px)), int(np.floor(py))
            fx, fy = px - x0, py - y0
            b = 1.0 if weight is None else float(weight[y, x])
            for xi, yi, wc in ((x0, y0, (1 - fx) * (1 - fy)), (x0 + 1, y0, fx * (1 - fy)),
                               (x0, y0 + 1, (1 - fx) * fy), (x0 + 1, y0 + 1, fx * fy)):
                if 0 <= xi < W and 0 <= yi < H:
                    den[yi, xi] += wc * b
                    num[yi, xi] += wc * b * image[y, x]
    return num, den


def test_splat_forward_against_reference():
    from endowave_cl.baselines import splat_forward
    rng = np.random.default_rng(8)
    H, W = 9, 11
    image = rng.uniform(0, 1, (H, W, 3)).astype(np.float32)
    disp = rng.uniform(-3, 3, (H, W, 2)).astype(np.float32)      # some pixels leave the image
    disp[2, 3] = np.nan                                          # a non-finite motion splats nothing
    weight = (rng.uniform(0, 1, (H, W)) > 0.3).astype(np.float32)
    for wt in (None, weight):
        num, den = splat_forward(image, disp, wt)
        ref_num, ref_den = _splat_ref(image, disp, wt)
        np.testing.assert_allclose(num, ref_num, atol=1e-5)
        np.testing.assert_allclose(den, ref_den, atol=1e-5)
    # a pixel that reaches nothing adds nothing anywhere, whatever its value
    bad = image.copy()
    bad[2, 3] = np.nan
    num, den = splat_forward(bad, disp)
    assert np.isfinite(num).all()
    np.testing.assert_allclose(num, _splat_ref(image, disp)[0], atol=1e-5)
    # an integer translation moves the image exactly, and leaves the uncovered border empty
    num, den = splat_forward(image, np.broadcast_to(np.float32([2.0, 1.0]), (H, W, 2)).copy())
    np.testing.assert_allclose(num[1:, 2:], image[:-1, :-2], atol=1e-6)
    np.testing.assert_array_equal(den[1:, 2:], 1.0)
    assert den[0].max() == 0 and den[:, :2].max() == 0


def test_between_target_splats_the_frames_along_the_models_motion():
    """model_fwd: the frames pushed forward along the model's motion from their own times.  The
    exact motion gives the translated frame inside; pixels no frame reaches keep the backward
    prediction (model_disp's); a still model gives the two frames' mean."""
    from endowave_cl.baselines import mean_interpolation
    from endowave_cl.train.between import between_target
    scene, pair, _ = _scene_and_pair()
    H, W = scene.height, scene.width
    inner = (slice(6, -6), slice(6, -6))
    flow_only, w0, t0 = between_target(scene, pair, 0.25)
    back = np.broadcast_to(np.float32([-1.0, 0.5]), (H, W, 2)).copy()   # frame at s -> frame 0
    g0 = -back                                                          # frame 0 -> s
    g1 = np.broadcast_to(np.float32([-3.0, 1.5]), (H, W, 2)).copy()     # frame 2 -> s
    image, w, t = between_target(scene, pair, 0.25, model_disp=back, model_weight=1.0, model_fwd=(g0, g1))
    assert t == t0
    np.testing.assert_array_equal(w, w0)
    np.testing.assert_allclose(image[inner], flow_only[inner], atol=2e-3)
    still = np.zeros((H, W, 2), np.float32)
    image, _, _ = between_target(scene, pair, 0.25, model_disp=still, model_weight=1.0, model_fwd=(still, still))
    np.testing.assert_allclose(image, mean_interpolation(scene.frames[0].image, scene.frames[2].image, 0.25),
                               atol=1e-6)
    # motion that carries everything out of the image: nothing is splatted, the backward one stays
    away = np.full((H, W, 2), 1e3, np.float32)
    backward, _, _ = between_target(scene, pair, 0.25, model_disp=back, model_weight=0.5)
    image, _, _ = between_target(scene, pair, 0.25, model_disp=back, model_weight=0.5, model_fwd=(away, away))
    np.testing.assert_array_equal(image, backward)


def test_reversed_splat_pushes_the_image_forward():
    """reversed_splat: a uniform motion reverses to itself, so the pushed image is the image sampled
    backward along it (bicubic, the same values to rounding); an integer motion moves it exactly and
    leaves the uncovered border unreached; tool pixels (source weight 0) reach nothing."""
    from endowave_cl.baselines import sample_displaced
    from endowave_cl.train.between import reversed_splat
    rng = np.random.default_rng(9)
    H, W = 12, 15
    image = rng.uniform(0, 1, (H, W, 3)).astype(np.float32)
    half = np.broadcast_to(np.float32([0.5, -0.25]), (H, W, 2)).copy()
    pushed, reach = reversed_splat(image, half)
    inner = (slice(1, -1), slice(1, -1))
    np.testing.assert_allclose(reach[inner], 1.0, atol=1e-6)
    np.testing.assert_allclose(pushed[inner], sample_displaced(image, -half, "cubic")[inner], atol=1e-5)
    step = np.broadcast_to(np.float32([2.0, 1.0]), (H, W, 2)).copy()
    pushed, reach = reversed_splat(image, step)
    np.testing.assert_allclose(pushed[1:, 2:], image[:-1, :-2], atol=1e-6)
    assert reach[0].max() == 0 and reach[:, :2].max() == 0
    tool = np.ones((H, W), np.float32)
    tool[:, :5] = 0.0
    _, reach = reversed_splat(image, step, tool)
    assert reach[:, :7].max() == 0 and reach[1:, 8:].min() == pytest.approx(1.0)


def test_reversed_splat_interpolation_takes_what_one_frame_cannot_reach_from_the_other():
    """reversed_splat_interpolation: frame 0 pushed 3 px right leaves its first three columns
    unreached, and there the frame at s is frame 1's pushed image alone; where both reach it is the
    (1 - s, s) blend; where neither does, the fill."""
    from endowave_cl.data.scene import Frame
    from endowave_cl.train.between import reversed_splat_interpolation
    rng = np.random.default_rng(10)
    H, W = 10, 14
    i0, i1 = (rng.uniform(0, 1, (H, W, 3)).astype(np.float32) for _ in range(2))
    f0, f1 = Frame(0, 0.0, i0, None, None, None), Frame(1, 1.0, i1, None, None, None)
    g0 = np.broadcast_to(np.float32([3.0, 0.0]), (H, W, 2)).copy()
    still = np.zeros((H, W, 2), np.float32)
    fill = np.full((H, W, 3), 7.0, np.float32)
    s = 0.25
    image = reversed_splat_interpolation(f0, f1, g0, still, s, fill)
    np.testing.assert_allclose(image[:, :3], i1[:, :3], atol=1e-6)
    np.testing.assert_allclose(image[:, 3:], (1 - s) * i0[:, :-3] + s * i1[:, 3:], atol=1e-6)
    away = np.full((H, W, 2), 1e3, np.float32)
    image = reversed_splat_interpolation(f0, f1, away, away, s, fill)
    np.testing.assert_array_equal(image, fill)


def test_reversed_splat_interpolation_counts_a_frame_once_where_its_motion_converges():
    """Where frame 0's motion converges (every even column moved one pixel right, onto the odd
    column beside it: a splatted weight of 2 there) and frame 1 reaches the pixel once, the frame
    at s is the (1 - s, s) blend of the two pushed frames: a reach above 1 counts as 1.  Where
    frame 0 reaches thinly (half a pixel's weight), its weight scales with its reach."""
    from endowave_cl.data.scene import Frame
    from endowave_cl.train.between import reversed_splat, reversed_splat_interpolation
    rng = np.random.default_rng(11)
    H, W = 8, 12
    i0, i1 = (rng.uniform(0, 1, (H, W, 3)).astype(np.float32) for _ in range(2))
    f0, f1 = Frame(0, 0.0, i0, None, None, None), Frame(1, 1.0, i1, None, None, None)
    still = np.zeros((H, W, 2), np.float32)
    s = 0.25
    g0 = np.zeros((H, W, 2), np.float32)
    g0[:, 0::2, 0] = 1.0
    pushed0, reach0 = reversed_splat(i0, g0)
    odd = np.zeros((H, W), bool)
    odd[:, 1::2] = True
    np.testing.assert_allclose(reach0[odd], 2.0, atol=1e-6)
    image = reversed_splat_interpolation(f0, f1, g0, still, s, np.zeros((H, W, 3), np.float32))
    np.testing.assert_allclose(image[odd], ((1 - s) * pushed0 + s * i1)[odd], atol=1e-6)
    np.testing.assert_allclose(image[~odd], i1[~odd], atol=1e-6)      # frame 0 reaches no even column
    # thin: a tool mask on every other column and a push of half a pixel give frame 0 half a weight
    tool = np.ones((H, W), np.float32)
    tool[:, 1::2] = 0.0
    f0 = Frame(0, 0.0, i0, None, tool, None)
    g0 = np.broadcast_to(np.float32([0.5, 0.0]), (H, W, 2)).copy()
    pushed0, reach0 = reversed_splat(i0, g0, tool)
    thin = (reach0 > 0.4) & (reach0 < 0.6)
    assert thin.sum() >= H * (W // 2 - 1)
    image = reversed_splat_interpolation(f0, f1, g0, still, s, np.zeros((H, W, 3), np.float32))
    a0 = (1 - s) * reach0[..., None]
    np.testing.assert_allclose(image[thin], ((a0 * pushed0 + s * i1) / (a0 + s))[thin], atol=1e-6)


def test_between_target_pushes_the_flows_frames_forward():
    """flow_splat: the flow pushes the frames forward (exact for a translation: the translated
    frame inside); the backward warps fill where no pixel lands (the borders the motion uncovers)."""
    from endowave_cl.train.between import between_target
    scene, pair, tex = _scene_and_pair()
    inner = (slice(6, -6), slice(6, -6))
    image, weight, t = between_target(scene, pair, 0.5, flow_splat=True)
    assert t == pytest.approx(0.5) and weight.min() == 1.0
    np.testing.assert_allclose(image[inner], scene.frames[1].image[inner], atol=2e-3)
    backward = between_target(scene, pair, 0.25)[0]
    pushed = between_target(scene, pair, 0.25, flow_splat=True)[0]
    np.testing.assert_allclose(pushed[inner], backward[inner], atol=1e-5)   # a uniform motion reverses exactly
    assert not np.allclose(pushed, backward, atol=1e-4)                # the borders differ


def _field(h, w, value):
    return np.broadcast_to(np.float32(value), (h, w, len(value)))


def test_consistent_flows_takes_the_estimator_whose_flow_returns():
    """consistent_flows: per pixel, the estimator whose forward and backward flows cancel wins
    (weights exp(-(e - e_min) / PUSH_TAU)); where the estimators are equally consistent, their mean;
    one estimator alone is returned as it is."""
    from types import SimpleNamespace
    from endowave_cl.train.between import PUSH_TAU, consistent_flows
    H, W = 24, 32
    right = SimpleNamespace(flow=np.full((H, W, 2), [1.0, 0.0], np.float32), flow_bw=np.full((H, W, 2), [-1.0, 0.0], np.float32))
    wrong = SimpleNamespace(flow=np.full((H, W, 2), [3.0, 0.0], np.float32), flow_bw=np.zeros((H, W, 2), np.float32))
    flow, flow_bw = consistent_flows([wrong, right])
    w_wrong = np.exp(-3.0 / PUSH_TAU) / (1 + np.exp(-3.0 / PUSH_TAU))     # its fb error is 3 px, the other's 0
    np.testing.assert_allclose(flow[4:-4, 4:-4], _field(16, 24, [1 + 2 * w_wrong, 0.0]), atol=1e-5)
    # the other way: right returns (error 0), wrong's zero flow_bw lands on its own 3 px flow (error 3)
    np.testing.assert_allclose(flow_bw[4:-4, 4:-4], _field(16, 24, [-(1 - w_wrong), 0.0]), atol=1e-5)
    other = SimpleNamespace(flow=np.full((H, W, 2), [1.0, 0.5], np.float32), flow_bw=np.full((H, W, 2), [-1.0, -0.5], np.float32))
    np.testing.assert_allclose(consistent_flows([right, other])[0][4:-4, 4:-4], _field(16, 24, [1.0, 0.25]), atol=1e-6)
    alone = consistent_flows([wrong])
    assert alone[0] is not None and np.array_equal(alone[0], wrong.flow) and np.array_equal(alone[1], wrong.flow_bw)


def test_between_target_pushes_once_along_the_consistent_flow():
    """flow_splat: the frames are pushed once, along the estimators' flows fused by consistency; a
    second estimator that fails to return to its start by many times PUSH_TAU is outvoted."""
    import dataclasses as dc
    from endowave_cl.train.between import PUSH_TAU, between_target, consistent_flows
    scene, pair, tex = _scene_and_pair()
    H, W = pair.flow.shape[:2]
    wrong = dc.replace(pair, flow=pair.flow + np.float32([12.0 * PUSH_TAU, 0.0]), flow_bw=np.zeros_like(pair.flow_bw))
    inner = (slice(8, -8), slice(8, -8))
    truth = scene.frames[1].image[inner]
    kw = dict(extra=[wrong], flow_splat=True, fuse="mean")
    fused = between_target(scene, pair, 0.5, **kw)[0]
    np.testing.assert_allclose(fused[inner], truth, atol=3e-3)
    given = between_target(scene, pair, 0.5, pushed_flows=consistent_flows([pair, wrong]), **kw)[0]
    np.testing.assert_array_equal(given, fused)


def test_draw_fraction_distributions():
    """uniform: the generator's draw itself; triangular: density 4 s / 4 (1 - s), so its quartiles
    are 1 / (2 sqrt 2), 1/2 and 1 - 1 / (2 sqrt 2), and 3/4 of the draws fall in [1/4, 3/4]."""
    from endowave_cl.train.between import draw_fraction
    a, b = np.random.default_rng(11), np.random.default_rng(11)
    assert [draw_fraction(a) for _ in range(5)] == [float(b.uniform(0.0, 1.0)) for _ in range(5)]
    rng = np.random.default_rng(0)
    s = np.array([draw_fraction(rng, "triangular") for _ in range(40000)])
    assert s.min() > 0.0 and s.max() < 1.0
    q = 1.0 / (2.0 * np.sqrt(2.0))
    np.testing.assert_allclose(np.quantile(s, [0.25, 0.5, 0.75]), [q, 0.5, 1.0 - q], atol=0.01)
    assert abs(np.mean((s >= 0.25) & (s <= 0.75)) - 0.75) < 0.01
    u = np.array([draw_fraction(rng, "uniform") for _ in range(40000)])
    assert abs(np.mean((u >= 0.25) & (u <= 0.75)) - 0.5) < 0.01


# ------------------------------------------------------------------ curved paths (between_path)
def _parabola(t):
    """[2]: where a point on an accelerating path is at time t (px); at the times i / 4 of
    _accelerating_scene's frames, whole pixels: (0, 0), (1, -1), (3, -1), (6, 0), (10, 2)."""
    i = 4.0 * t
    return np.float64([0.5, -1.5]) * i + np.float64([0.5, 0.5]) * i * i


def test_path_displacement_follows_the_parabola():
    """path_displacement through three positions at unequal time steps gives the point's exact
    place on its parabola at every fraction, from either frame of the pair; without an outer
    flow, or with one on the same side in time, it is the straight s flow."""
    from endowave_cl.train.between import path_displacement
    H, W = 3, 4
    f = lambda v: np.broadcast_to(np.float32(v), (H, W, 2)).copy()          # noqa: E731
    for t0, t1, t_out in ((0.3, 0.8, 0.05), (0.8, 0.3, 1.0), (0.2, 0.6, -0.6)):
        flow, outer = f(_parabola(t1) - _parabola(t0)), f(_parabola(t_out) - _parabola(t0))
        for s in (0.0, 0.25, 0.5, 0.9, 1.0):
            got = path_displacement(flow, s, t1 - t0, outer, t_out - t0)
            want = _parabola(t0 + s * (t1 - t0)) - _parabola(t0)
            np.testing.assert_allclose(got, f(want), atol=1e-5)
    flow, outer = f([2.0, -1.0]), f([5.0, 5.0])
    np.testing.assert_array_equal(path_displacement(flow, 0.25, 0.5), np.float32(0.25) * flow)
    np.testing.assert_array_equal(path_displacement(flow, 0.25, 0.5, outer, 0.7), np.float32(0.25) * flow)


def test_pair_bend_finds_the_frames_beyond_the_pair():
    """pair_bend: the first frame's flow to the training frame before the pair and the second's to
    the one after it, per source and for the fused flows, with their time offsets; a side with no
    adjoining pair stays None, and a pair with neither has no bend."""
    from types import SimpleNamespace
    from endowave_cl.train.between import pair_bend
    times = [0.0, 0.1, 0.3, 0.4, 0.7]
    scene = SimpleNamespace(frames=[SimpleNamespace(time=t) for t in times])

    def pair(a, b, tag):
        return SimpleNamespace(src=a, dst=b, flow=np.full((2, 2, 2), tag, np.float32),
                               flow_bw=np.full((2, 2, 2), -tag, np.float32))

    pairs = [pair(0, 1, 1.0), pair(1, 2, 2.0), pair(2, 3, 3.0), pair(4, 4, 9.0)]
    extra = {id(p): pair(p.src, p.dst, 10 * p.flow[0, 0, 0]) for p in pairs}
    sources = lambda p: [p, extra[id(p)]]                                      # noqa: E731
    fused = lambda i: (pairs[i].flow + 0.5, pairs[i].flow_bw - 0.5)           # noqa: E731
    b = pair_bend(scene, pairs, 1, sources, fused)
    assert (b.span, b.before_span, b.after_span) == pytest.approx((0.2, -0.1, 0.1))
    assert [x[0, 0, 0] for x in b.before] == [-1.0, -10.0]         # frame 1 -> frame 0, per source
    assert [x[0, 0, 0] for x in b.after] == [3.0, 30.0]            # frame 2 -> frame 3, per source
    assert b.fused[0][0, 0, 0] == -1.5 and b.fused[1][0, 0, 0] == 3.5
    first = pair_bend(scene, pairs, 0, sources)
    assert first.before == [None, None] and first.after[0][0, 0, 0] == 2.0 and first.fused == (None, None)
    last = pair_bend(scene, pairs, 2, sources)
    assert last.before[1][0, 0, 0] == -20.0 and last.after == [None, None]
    assert pair_bend(scene, pairs, 3, sources) is None


def _accelerating_scene(H=40, W=56):
    """Frames 0..4 of a texture on the path _parabola at times i / 4; frame 2 held out. Returns
    (scene, pairs in frame order) with exact translation flows."""
    from endowave_cl.camera import Camera
    from endowave_cl.data.flow import FlowPair
    from endowave_cl.data.scene import Frame, Scene
    tex = _textured(H, W)
    cam = Camera(width=W, height=H, fx=50.0, fy=50.0, cx=W / 2, cy=H / 2, viewmat=np.eye(4, dtype=np.float32))
    times = [i / 4 for i in range(5)]
    frames = [Frame(i, t, _shifted(tex, *_parabola(t), H, W), None, None, cam) for i, t in enumerate(times)]
    scene = Scene(path=None, frames=frames, train_indices=[0, 1, 3, 4], test_indices=[2], near=0.1, far=10.0,
                  width=W, height=H, has_depth=False, has_masks=False)
    ones = np.ones((H, W), np.float32)

    def flow_pair(a, b):
        d = np.broadcast_to(np.float32(_parabola(times[b]) - _parabola(times[a])), (H, W, 2)).copy()
        return FlowPair(a, b, d, ones.copy(), -d, ones.copy())

    return scene, [flow_pair(0, 1), flow_pair(1, 3), flow_pair(3, 4)]


def test_between_target_on_curved_paths_is_the_held_out_frame():
    """On a texture that speeds up, the pair around the held-out frame bent by its neighbours
    predicts that frame (backward warps, and pushed along the fused flows); the straight paths
    miss it by the acceleration's share, half a pixel each way here."""
    from endowave_cl.train.between import between_target, consistent_flows, pair_bend
    scene, pairs = _accelerating_scene()
    fused = lambda i: consistent_flows([pairs[i]])                            # noqa: E731
    bend = pair_bend(scene, pairs, 1, lambda p: [p], fused)
    truth = scene.frames[2].image
    inner = (slice(8, -8), slice(8, -8))
    for kw in (dict(), dict(flow_splat=True)):
        curved = between_target(scene, pairs[1], 0.5, bend=bend, **kw)[0]
        straight = between_target(scene, pairs[1], 0.5, **kw)[0]
        err_curved = np.abs(curved[inner] - truth[inner]).mean()
        np.testing.assert_allclose(curved[inner], truth[inner], atol=2e-3)
        assert np.abs(straight[inner] - truth[inner]).mean() > 5 * err_curved


def test_bend_around_estimates_the_frames_beyond_a_held_out_pair():
    """bend_around (the teacher tools' Bend of a pair that need not be a training pair): the flows
    to the nearest training frames beyond the pair come from flows_of, per estimator, and give the
    training pairs' own Bend; frames_beyond finds those frames."""
    from endowave_cl.train.between import bend_around, consistent_flows, frames_beyond, pair_bend
    scene, pairs = _accelerating_scene()
    assert frames_beyond(scene, 1, 3) == (0, 4) and frames_beyond(scene, 0, 1) == (None, 3)
    asked = []

    def flows_of(a, b, m):
        asked.append((a, b, m))
        return np.broadcast_to(np.float32(_parabola(a / 4) - _parabola(b / 4)) * -1, pairs[0].flow.shape).copy()

    got = bend_around(scene, [pairs[1], pairs[1]], ["x", "y"], flows_of, fused=True)
    want = pair_bend(scene, pairs, 1, lambda p: [p, p], lambda i: consistent_flows([pairs[i]]))
    assert {(a, b) for a, b, _ in asked} == {(0, 1), (1, 0), (3, 4), (4, 3)} and {m for *_, m in asked} == {"x", "y"}
    assert (got.span, got.before_span, got.after_span) == pytest.approx((want.span, want.before_span, want.after_span))
    for g, w in zip(got.before + got.after + list(got.fused), want.before + want.after + list(want.fused)):
        np.testing.assert_allclose(g, w, atol=1e-5)
