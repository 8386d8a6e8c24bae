"""Every TrainConfig key changes what it claims to (issue #15: "every setting in TrainConfig and
actually used").

One check per key, parametrised: the key is set to a value other than its default and the check
looks at the object that consumes it (the training loop with its steps stubbed, the learning-rate
map, the initial Gaussians, density control, the device losses, the run loader) for the effect the
key's comment in train/config.py promises.  CHECKS must name every key: a new key without a check
fails test_every_key_has_a_check.
"""
from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from conftest import tiny_config
from endowave_cl.errors import EndowaveError
from endowave_cl.gaussians import Gaussians
from endowave_cl.train.config import KEYS, TrainConfig, load_config
from endowave_cl.train.densify import densify_and_prune, logit

QUICK = dict(init_points=50, use_flow=False, init_velocity=False, between_prob=0.0,
             between_flows="", between_path="linear", between_levels=0)
# cheap trainers: no flow; checks of one in-between key use one estimator, straight paths (the
# between_path check draws both kinds) and the continuous draw, whose target is exact at any s (the
# between_levels check keeps them per grid point)


@pytest.fixture(scope="module")
def scene(tiny_scene):
    from endowave_cl.data.scene import load_scene
    return load_scene(tiny_scene)


def _trainer(scene, rt, tmp_path, **kw):
    from endowave_cl.train.trainer import Trainer
    return Trainer(scene, tiny_config(**{**QUICK, **kw}), tmp_path / "run", rt, log=lambda s: None, resume=False)


def _target_kw(tr, **over):
    """between_target's keywords as the trainer's in-between keys set them, with over's changes."""
    c = tr.cfg
    return {**dict(fuse=c.between_fuse, flow_splat=c.between_flow_splat), **over}


# ------------------------------------------------------------------ the training loop, steps stubbed
def _loop(scene, rt, tmp_path, **kw):
    """Run Trainer.train with train_step, density control's host work (densify_and_prune), the
    opacity reset, evaluation and saving replaced by recorders: {event: [steps]}."""
    import endowave_cl.train.trainer as trainer_module
    tr = _trainer(scene, rt, tmp_path, **kw)
    ev = {"densify": [], "reset": [], "evaluate": [], "save": [], "prune_big": []}

    def step(k):
        tr.step += 1
        return {"total": 1.0, "psnr": 20.0}

    def densify_and_prune(g, grad_accum, count, max_radius, cfg, extent, prune_big=False, stats=None):
        ev["densify"].append(tr.step)
        ev["prune_big"].append(prune_big)
        stats.update(cloned=0, split=0, pruned=0, replaced=0, is_new=np.zeros(len(g), bool))
        return g, np.arange(len(g))

    tr.train_step = step
    tr.reset_opacity = lambda: ev["reset"].append(tr.step)
    tr.evaluate = lambda: ev["evaluate"].append(tr.step) or {"psnr": 0.0, "psnr_masked": 0.0, "ssim": 0.0}
    tr.save = lambda: ev["save"].append(tr.step)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(trainer_module, "densify_and_prune", densify_and_prune)   # densify's, as the trainer imports it
        tr.train(progress=False)
    ev["steps"] = tr.step
    ev["history"] = [h["step"] for h in tr.history]
    return ev


LOOP = dict(iterations=6, densify_from=2, densify_every=2, densify_until=4, log_every=3)


def _loop_effect(key, value, what):
    def check(scene, rt, tmp_path):
        base = _loop(scene, rt, tmp_path / "a", **LOOP)
        new = _loop(scene, rt, tmp_path / "b", **{**LOOP, key: value})
        return what(base, new)
    return check


def _iterations(b, n):
    assert (b["steps"], n["steps"]) == (6, 4)


def _log_every(b, n):
    assert b["history"] == [3, 6] and n["history"] == [2, 4, 6]


def _eval_every(b, n):
    assert b["evaluate"] == [6] and n["evaluate"] == [2, 4, 6]   # every 2 steps, and the final one


def _checkpoint_every(b, n):
    assert b["save"] == [6] and n["save"] == [3, 6, 6]           # every 3 steps, and the final one


def _densify_from(b, n):
    assert b["densify"] == [2, 4] and n["densify"] == [4]


def _densify_every(b, n):
    assert b["densify"] == [2, 4] and n["densify"] == [3]


def _densify_until(b, n):
    assert b["densify"] == [2, 4] and n["densify"] == [2, 4, 6]


def _opacity_reset_every(b, n):
    # resets only before densify_until (4: as 3DGS, not at it); large screen / world sizes are
    # pruned once past the first reset
    assert b["reset"] == [] and n["reset"] == [2]
    assert b["prune_big"] == [False, False] and n["prune_big"] == [False, True]


# ------------------------------------------------------------------ the trainer's own settings
def _minutes(scene, rt, tmp_path):
    assert _trainer(scene, rt, tmp_path / "a")._start_budget() is None
    plan = _trainer(scene, rt, tmp_path / "b", minutes=2.0)._start_budget()
    assert plan is not None and plan.seconds == 120.0


def _seed(scene, rt, tmp_path):
    a = _trainer(scene, rt, tmp_path / "a").params["means"].get()
    b = _trainer(scene, rt, tmp_path / "b", seed=1).params["means"].get()
    assert a.shape == b.shape and not np.array_equal(a, b)


def _deterministic(scene, rt, tmp_path, monkeypatch):
    import endowave_cl.train.trainer as trainer_module
    seen = []
    real = trainer_module.render_backward

    def spy(*a, **kw):
        seen.append(kw["deterministic"])
        return real(*a, **kw)

    monkeypatch.setattr(trainer_module, "render_backward", spy)
    for run, value in (("a", False), ("b", True)):
        tr = _trainer(scene, rt, tmp_path / run, deterministic=value)
        tr.train_step(tr.scene.train_indices[0])
    assert seen == [None, True]   # None: the device's default (CPU: deterministic); True: forced


def _downscale(scene, rt, tmp_path):
    from endowave_cl.checkpoint import checkpoint_path, save_checkpoint
    from endowave_cl.run_io import load_run
    widths = []
    for run, value in (("a", 1.0), ("b", 2.0)):
        d = tmp_path / run
        d.mkdir()
        cfg = TrainConfig(downscale=value)
        (d / "config.json").write_text(json.dumps({**cfg.to_dict(), "scene": str(scene.path)}))
        save_checkpoint(checkpoint_path(d, 1), Gaussians.random(3), None, 1, cfg.to_dict())
        widths.append(load_run(d).scene.width)
    assert widths == [scene.width, scene.width // 2]


def _split(scene, rt, tmp_path):
    """"validation" holds the validation frames out of training and scores them; the run loader
    applies the run's split."""
    from endowave_cl.checkpoint import checkpoint_path, save_checkpoint
    from endowave_cl.data.scene import validation_indices
    from endowave_cl.run_io import load_run
    got = {}
    for run, value in (("a", "test"), ("b", "validation")):
        d = tmp_path / run
        d.mkdir()
        cfg = TrainConfig(split=value)
        (d / "config.json").write_text(json.dumps({**cfg.to_dict(), "scene": str(scene.path)}))
        save_checkpoint(checkpoint_path(d, 1), Gaussians.random(3), None, 1, cfg.to_dict())
        got[value] = load_run(d).scene
    val = validation_indices(len(scene.frames))
    assert val and got["validation"].test_indices == val
    assert got["test"].test_indices == scene.test_indices
    assert set(got["validation"].train_indices) == set(scene.train_indices) - set(val)
    with pytest.raises(EndowaveError, match="key 'split' must be one of"):
        load_config(None, {"split": "train"})


def _recipe(scene, rt, tmp_path):
    """A recipe sets the values it names before the file and the overrides, and is recorded."""
    from endowave_cl.train.config import RECIPES
    cfg = load_config(None, {"recipe": "paper"})
    assert cfg.recipe == "paper" and cfg.between_prob == 0.0 and cfg.iterations == 30000
    assert all(getattr(cfg, k) == v for k, v in RECIPES["paper"].items())
    assert load_config(None, {"recipe": "paper", "between_prob": "0.25"}).between_prob == 0.25
    assert load_config(None).between_prob == TrainConfig().between_prob
    with pytest.raises(EndowaveError, match="unknown recipe 'fast'"):
        load_config(None, {"recipe": "fast"})


def _init_points(scene, rt, tmp_path):
    assert len(_trainer(scene, rt, tmp_path / "a").params["means"]) == QUICK["init_points"]
    assert len(_trainer(scene, rt, tmp_path / "b", init_points=80).params["means"]) == 80


def _init_time_scale(scene, rt, tmp_path):
    for run, value in (("a", 0.2), ("b", 0.05)):
        s = _trainer(scene, rt, tmp_path / run, init_time_scale=value).params["scales"].get()
        np.testing.assert_allclose(np.exp(s[:, 3]), value, rtol=1e-5)   # still Gaussians: t is axis 3


def _init_velocity(scene, rt, tmp_path):
    from endowave_cl.gaussians import download
    still = download(_trainer(scene, rt, tmp_path / "a").params)
    moving = download(_trainer(scene, rt, tmp_path / "b", init_velocity=True).params)
    from endowave_cl.train.motion import motion_of
    from endowave_cl.gaussians import covariance_4d
    assert np.abs(motion_of(covariance_4d(still))[2]).max() < 1e-6
    assert np.abs(motion_of(covariance_4d(moving))[2]).max() > 1e-3


def _flow_method(scene, rt, tmp_path, monkeypatch):
    import endowave_cl.data.flow as flow_module
    import endowave_cl.train.between as between_module
    import endowave_cl.train.trainer as trainer_module
    seen = []
    fake = lambda sc, method, progress, max_pixels=0: seen.append(method) or {}   # noqa: E731
    for mod in (flow_module, between_module, trainer_module):   # data.flow's, as the trainer imports it
        monkeypatch.setattr(mod, "flow_for_scene", fake)
    _trainer(scene, rt, tmp_path / "a", use_flow=True)
    _trainer(scene, rt, tmp_path / "b", use_flow=True, flow_method="tvl1")
    assert seen == ["dis_fine", "tvl1"]


def _flow_max_pixels(scene, rt, tmp_path, monkeypatch):
    """Every estimator's flow (the pseudo ground truth and the in-between target's) is asked for
    at the configured pixel budget (data/flow.py estimation_size does the rest)."""
    import endowave_cl.data.flow as flow_module
    real = flow_module.flow_for_scene
    seen = []

    def spy(sc, method, progress, max_pixels=0):
        seen.append((method, max_pixels))
        return real(sc, method=method, progress=False, max_pixels=max_pixels)
    import endowave_cl.train.between as between_module
    import endowave_cl.train.trainer as trainer_module
    for mod in (flow_module, between_module, trainer_module):   # data.flow's, as the trainer imports it
        monkeypatch.setattr(mod, "flow_for_scene", spy)
    from endowave_cl.train.config import FLOW_MAX_PIXELS
    _trainer(scene, rt, tmp_path / "a", use_flow=True, between_prob=0.5, between_flows="dis")
    _trainer(scene, rt, tmp_path / "b", use_flow=True, between_prob=0.5, between_flows="dis", flow_max_pixels=600)
    assert seen == [("dis_fine", FLOW_MAX_PIXELS), ("dis", FLOW_MAX_PIXELS), ("dis_fine", 600), ("dis", 600)]


def _sh_degree(scene, rt, tmp_path):
    """-1 (the default): degree 1 where every training frame shares one camera centre (the tiny
    scene), 3 where the centres differ; 0..3: that degree; a resumed run keeps its checkpoint's."""
    def degree(tr):
        return int(round(math.sqrt(tr.params["sh"].shape[2]))) - 1
    assert scene.one_viewpoint()
    tr = _trainer(scene, rt, tmp_path / "a")
    assert degree(tr) == 1 and tr.cfg.sh_degree == 1
    assert json.loads((tmp_path / "a" / "run" / "config.json").read_text())["sh_degree"] == 1
    assert degree(_trainer(scene, rt, tmp_path / "b", sh_degree=2)) == 2
    moved = _moved_camera(scene)
    assert not moved.one_viewpoint()
    assert degree(_trainer(moved, rt, tmp_path / "c")) == 3
    tr = _trainer(scene, rt, tmp_path / "d", sh_degree=0)
    tr.save()
    tr._run.lock.release()   # as a finished run leaves its folder
    from endowave_cl.train.trainer import Trainer
    again = Trainer(scene, tiny_config(**QUICK), tmp_path / "d" / "run", rt, log=lambda s: None, resume=True)
    assert degree(again) == 0 and again.cfg.sh_degree == 0
    with pytest.raises(EndowaveError, match=r"key 'sh_degree' must be in \[-1, 3\]"):
        load_config(None, {"sh_degree": "4"})


def test_default_cap_counts_the_gaussians_alive_at_a_time(scene, rt, tmp_path):
    """max_gaussians = 0: at least MAX_GAUSSIANS_PER_PIXEL per pixel, raised to ALIVE_PER_PIXEL
    per pixel alive at a time when the initial Gaussians each live a short part of the sequence;
    a given cap is kept as given; a resumed run keeps the cap it started with."""
    from endowave_cl.gaussians import covariance_4d, download
    from endowave_cl.train.config import (ALIVE_PER_PIXEL, MAX_GAUSSIANS_PER_PIXEL,
                                          MAX_GAUSSIANS_PER_PIXEL_LIMIT)
    from endowave_cl.train.motion import temporal_coverage
    from endowave_cl.train.trainer import Trainer
    W, H = scene.width, scene.height
    floor = int(MAX_GAUSSIANS_PER_PIXEL * W * H)
    cfg = TrainConfig().resolve_density(W, H)
    assert cfg.max_gaussians == floor
    assert cfg.resolve_cap_for_lifetimes(W, H, coverage=1.0).max_gaussians == floor   # alive all along: the floor
    assert cfg.resolve_cap_for_lifetimes(W, H, coverage=0.05).max_gaussians == int(ALIVE_PER_PIXEL * W * H / 0.05) > floor
    bounded = cfg.resolve_cap_for_lifetimes(W, H, coverage=1e-9)       # bounded for memory
    assert bounded.max_gaussians == int(MAX_GAUSSIANS_PER_PIXEL_LIMIT * W * H)

    long_lived = _trainer(scene, rt, tmp_path / "a", init_time_scale=0.5)
    assert long_lived.cfg.max_gaussians == floor
    short = _trainer(scene, rt, tmp_path / "b", init_time_scale=0.02)
    g = download(short.params)
    cover = temporal_coverage(g.means[:, 3], np.sqrt(covariance_4d(g)[:, 3, 3])).mean()
    assert cover < 0.06
    assert short.cfg.max_gaussians == int(ALIVE_PER_PIXEL * W * H / cover) > floor
    assert json.loads((tmp_path / "b" / "run" / "config.json").read_text())["max_gaussians"] == short.cfg.max_gaussians
    assert _trainer(scene, rt, tmp_path / "c", init_time_scale=0.005, max_gaussians=77).cfg.max_gaussians == 77
    short.save()
    short._run.lock.release()   # as a finished run leaves its folder
    again = Trainer(scene, tiny_config(**QUICK), tmp_path / "b" / "run", rt, log=lambda s: None, resume=True)
    assert again.cfg.max_gaussians == short.cfg.max_gaussians


def test_default_iterations_visit_every_training_frame_alike(scene, rt, tmp_path):
    """iterations = 0: STEPS_PER_TRAINING_FRAME per training frame, at least BASE_ITERATIONS, with
    the schedule keys stretched by the same factor; a given step count keeps the keys as given."""
    from endowave_cl.train.config import BASE_ITERATIONS, SCALED_FIELDS, STEPS_PER_TRAINING_FRAME
    short = TrainConfig().resolve_iterations(BASE_ITERATIONS // STEPS_PER_TRAINING_FRAME)   # a short sequence: the floor
    assert short.iterations == BASE_ITERATIONS
    assert all(getattr(short, f) == getattr(TrainConfig(), f) for f in SCALED_FIELDS)
    n = 3 * BASE_ITERATIONS // STEPS_PER_TRAINING_FRAME                     # three times as many frames
    long = TrainConfig().resolve_iterations(n)
    assert long.iterations == STEPS_PER_TRAINING_FRAME * n > BASE_ITERATIONS
    r = long.iterations / BASE_ITERATIONS
    for f in ("densify_from", "densify_until", "opacity_reset_every"):
        assert getattr(long, f) == round(getattr(TrainConfig(), f) * r), f
    assert long.densify_until < long.iterations and long.opacity_reset_every >= long.densify_until  # no reset
    assert long.lr_position_steps == 0                                      # still "over all iterations"
    given = TrainConfig(iterations=123).resolve_iterations(n)
    assert given.iterations == 123 and given.densify_until == TrainConfig().densify_until

    tr = _trainer(scene, rt, tmp_path / "a", iterations=0)
    want = max(BASE_ITERATIONS, STEPS_PER_TRAINING_FRAME * len(scene.train_indices))
    assert tr.auto_iterations and tr.cfg.iterations == want
    assert json.loads((tmp_path / "a" / "run" / "config.json").read_text())["iterations"] == want
    assert not _trainer(scene, rt, tmp_path / "b", iterations=7).auto_iterations


def _moved_camera(scene):
    """The scene with its second training frame's camera moved sideways."""
    import copy
    moved = copy.copy(scene)
    moved.frames = list(scene.frames)
    k = scene.train_indices[1]
    f = copy.copy(scene.frames[k])
    f.camera = copy.copy(f.camera)
    f.camera.viewmat = f.camera.viewmat.copy()
    f.camera.viewmat[0, 3] += 0.05
    moved.frames[k] = f
    return moved


def _fixed(key, default):
    """The model layout is fixed in this version: the trainer builds it from the key, other values
    are refused with a one-line error."""
    def check(scene, rt, tmp_path):
        sh = _trainer(scene, rt, tmp_path / "a").params["sh"].shape      # [N, NT+1, (L+1)^2, 3]
        layout = {"temporal_freqs": sh[1] - 1, "sh_degree": int(round(math.sqrt(sh[2]))) - 1}
        assert layout[key] == default
        with pytest.raises(EndowaveError, match=f"key '{key}' must be {default}"):
            load_config(None, {key: str(default - 1)})
    return check


# ------------------------------------------------------------------ learning rates
def _lrs(cfg, step=0, extent=2.0):
    from endowave_cl.train.trainer import Trainer
    cfg = cfg.resolve_iterations(55)   # as the trainer does before its first step (55 training frames)
    return Trainer.group_lrs(SimpleNamespace(cfg=cfg, extent=extent), step)


def _lr(key, group, value):
    def check(scene, rt, tmp_path):
        assert _lrs(TrainConfig())[group] != value
        assert _lrs(TrainConfig(**{key: value}))[group] == pytest.approx(value)
    return check


def _lr_position_init(scene, rt, tmp_path):
    assert _lrs(TrainConfig(lr_position_init=3e-4))["means"] == pytest.approx(3e-4 * 2.0)   # x extent


def _lr_position_final(scene, rt, tmp_path):
    c = TrainConfig(iterations=100, lr_position_final=5e-6)
    assert _lrs(c, 100)["means"] == pytest.approx(5e-6 * 2.0)
    assert _lrs(TrainConfig(iterations=100), 100)["means"] == pytest.approx(TrainConfig().lr_position_final * 2.0)


def _lr_position_steps(scene, rt, tmp_path):
    c = TrainConfig(iterations=100, lr_position_steps=10)
    assert _lrs(c, 10)["means"] == pytest.approx(c.lr_position_final * 2.0)
    assert _lrs(TrainConfig(iterations=100), 10)["means"] > 2 * c.lr_position_final * 2.0


def _lr_anneal_final(scene, rt, tmp_path):
    """Every group but the means is multiplied by 1 up to densify_until, by the factor at the last
    step and by its square root half-way (log-linear); the means keep their own decay."""
    c = TrainConfig(iterations=100, densify_until=60, lr_anneal_final=0.04)
    base = {s: _lrs(TrainConfig(iterations=100, densify_until=60, lr_anneal_final=1.0), s) for s in (60, 80, 100)}
    for s, factor in ((60, 1.0), (80, 0.2), (100, 0.04)):
        got = _lrs(c, s)
        assert got["means"] == base[s]["means"]
        for g in ("means_t", "scales", "scales_t", "quat_l", "quat_r", "opacity", "sh", "sh_rest", "phase"):
            assert got[g] == pytest.approx(factor * base[s][g], rel=1e-9), (s, g)


def _lr_features_rest_divisor(scene, rt, tmp_path):
    assert _lrs(TrainConfig())["sh_rest"] == pytest.approx(2.5e-3 / 20)
    assert _lrs(TrainConfig(lr_features_rest_divisor=5.0))["sh_rest"] == pytest.approx(2.5e-3 / 5)


# ------------------------------------------------------------------ density control (host)
def _pair(n=4, scale=math.log(0.005), opacity=0.5):
    g = Gaussians.random(n, seed=0)
    g.scales[:] = scale
    g.scales[:, 3] = math.log(0.2)
    g.opacity[:] = logit(opacity)
    g.quat_l[:] = g.quat_r[:] = [1, 0, 0, 0]
    return g


def _densify(g, cfg, grad=1e-3, radius=1.0, prune_big=False):
    from dataclasses import replace
    from endowave_cl.train.config import DENSIFY_GRAD_THRESHOLD
    if cfg.densify_grad_threshold <= 0:      # TrainConfig()'s 0, as resolve_density makes it for small frames
        cfg = replace(cfg, densify_grad_threshold=DENSIFY_GRAD_THRESHOLD)
    info = {}
    n = len(g)
    out, _ = densify_and_prune(g, np.full(n, grad), np.ones(n), np.full(n, radius), cfg, 1.0,
                               prune_big=prune_big, stats=info)
    return out, info


def _densify_effect(what):
    def check(scene, rt, tmp_path):
        what()
    return check


def _densify_grad_threshold():
    assert _densify(_pair(), TrainConfig(), grad=3e-4)[1]["cloned"] == 4
    assert _densify(_pair(), TrainConfig(densify_grad_threshold=5e-4), grad=3e-4)[1]["cloned"] == 0


def _percent_dense():
    assert _densify(_pair(), TrainConfig())[1]["cloned"] == 4                 # 0.005 <= 0.01: clone
    info = _densify(_pair(), TrainConfig(percent_dense=0.001))[1]             # 0.005 > 0.001: split
    assert info["cloned"] == 0 and info["split"] == 4


def _split_children():
    big = dict(scale=math.log(0.05))
    assert len(_densify(_pair(**big), TrainConfig())[0]) == 8
    assert len(_densify(_pair(**big), TrainConfig(split_children=3))[0]) == 12


def _split_scale_divisor():
    from endowave_cl.gaussians import covariance_4d
    from endowave_cl.train.motion import spatial_size
    g = _pair(scale=math.log(0.01))
    g.scales[:, 0] = math.log(0.05)        # the major axis (x) is the one divided
    sizes = [spatial_size(covariance_4d(_densify(g, TrainConfig(split_scale_divisor=d))[0])).max()
             for d in (1.6, 3.0)]
    assert sizes[0] == pytest.approx(0.05 / 1.6, rel=1e-3) and sizes[1] == pytest.approx(0.05 / 3.0, rel=1e-3)


def _cap_turnover():
    g = _pair()
    g.opacity[:2] = logit(0.01)                    # two faint Gaussians, not candidates below
    grad = np.array([0, 0, 1e-3, 1e-3])
    out = [densify_and_prune(g, grad, np.ones(4), np.ones(4),
                             TrainConfig(max_gaussians=4, densify_grad_threshold=2e-4, cap_turnover=t), 1.0)[0]
           for t in (0.0, 0.5)]
    assert len(out[0]) == len(out[1]) == 4           # at the cap either way
    assert (out[0].opacity == g.opacity).all()        # 0: nothing replaced, nothing cloned
    assert (out[1].opacity > logit(0.02)).all()       # 0.5: the faint two gave their rows to clones


def _prune_opacity():
    low = dict(opacity=0.004)
    assert len(_densify(_pair(**low), TrainConfig(), grad=0)[0]) == 0        # below 0.005: pruned
    assert len(_densify(_pair(**low), TrainConfig(prune_opacity=0.001), grad=0)[0]) == 4


def _prune_screen_size():
    assert len(_densify(_pair(), TrainConfig(), grad=0, radius=30.0, prune_big=True)[0]) == 0
    assert len(_densify(_pair(), TrainConfig(prune_screen_size=40.0), grad=0, radius=30.0, prune_big=True)[0]) == 4


def _prune_world_size():
    assert len(_densify(_pair(), TrainConfig(), grad=0, prune_big=True)[0]) == 4       # 0.005 < 0.1
    assert len(_densify(_pair(), TrainConfig(prune_world_size=0.001), grad=0, prune_big=True)[0]) == 0


def _max_gaussians():
    assert len(_densify(_pair(), TrainConfig())[0]) == 8                       # 0: no cap
    assert len(_densify(_pair(), TrainConfig(max_gaussians=6))[0]) == 6


def _opacity_reset_value(scene, rt, tmp_path):
    from endowave_cl.train.densify import sigmoid
    tr = _trainer(scene, rt, tmp_path / "a", opacity_reset_value=0.05)
    before = tr.params["opacity"].get()
    tr.reset_opacity()
    after = sigmoid(tr.params["opacity"].get())
    assert (sigmoid(before) > 0.05).any()
    assert after.max() == pytest.approx(0.05, rel=1e-5)


# ------------------------------------------------------------------ the losses (device)
def _losses(rt, cfg):
    """parts of image_losses_and_grad on a fixed random 24x20 frame (depth, flow, a mask), with the
    wavelet settings taken from cfg as the trainer takes them."""
    import pyopencl.array as cla
    from endowave_cl.layout import CHANNELS, DEPTH, FLOW
    from endowave_cl.train.device_losses import image_losses_and_grad, prepare_targets
    rng = np.random.default_rng(0)
    H, W = 20, 24
    feats = rng.uniform(0, 1, (H, W, CHANNELS)).astype(np.float32)
    feats[..., FLOW] *= 20.0                                               # flow errors beyond 4 px
    tgt = prepare_targets(rt, rng.uniform(0, 1, (H, W, 3)), (rng.uniform(0, 1, (H, W)) > 0.2),
                          rng.uniform(0.5, 1, (H, W)), rng.uniform(-1, 1, (H, W, 2)), None)
    total, parts, _ = image_losses_and_grad(rt, cla.to_device(rt.queue, feats), tgt, cfg,
                                            {"depth": DEPTH, "flow": FLOW.start}, cfg.wavelet_config())
    return parts




def _between_prob(scene, rt, tmp_path):
    """between_prob: the fraction of steps rendered between two training frames (0: none, 1: all)."""
    train_times = {scene.frames[k].time for k in scene.train_indices}
    for prob, want in ((0.0, 0), (1.0, 4)):
        tr = _trainer(scene, rt, tmp_path / str(prob), iterations=4, between_prob=prob, densify_from=100)
        times = []
        real = tr._step
        tr._step = lambda cam, t, t_next, dev, what, **kw: (times.append(t), real(cam, t, t_next, dev, what, **kw))[1]
        tr.train(progress=False)
        assert len(times) == 4 and sum(t not in train_times for t in times) == want


def _between_anneal_final(scene, rt, tmp_path):
    """between_anneal_final: the in-between chance is between_prob until densify_until, then falls
    linearly to between_prob x the factor at the last step; with factor 0 the last steps of a run
    are all at training frames."""
    c = TrainConfig(iterations=100, densify_until=60, between_prob=0.5, between_anneal_final=0.2)
    tr = SimpleNamespace(cfg=c)
    from endowave_cl.train.trainer import Trainer
    got = [Trainer.between_prob(tr, s) for s in (0, 60, 80, 100, 120)]
    assert got == pytest.approx([0.5, 0.5, 0.3, 0.1, 0.1], rel=1e-12)
    train_times = {scene.frames[k].time for k in scene.train_indices}
    tr = _trainer(scene, rt, tmp_path, iterations=6, between_prob=1.0, between_anneal_final=0.0,
                  densify_from=100, densify_until=3)
    times = []
    real = tr._step
    tr._step = lambda cam, t, t_next, dev, what, **kw: (times.append(t), real(cam, t, t_next, dev, what, **kw))[1]

    class HalfDraw:    # the trainer's generator, except that every chance draw is 0.5
        def __init__(self, rng):
            self._rng = rng

        def random(self):
            return 0.5

        def __getattr__(self, name):
            return getattr(self._rng, name)
    tr.rng = HalfDraw(tr.rng)
    tr.train(progress=False)
    # chances 1, 1, 1, 1 up to densify_until, then 2/3 and 1/3: only the last step drew below 0.5
    assert [t not in train_times for t in times] == [True] * 5 + [False]


def _average_last(scene, rt, tmp_path, monkeypatch):
    """average_last: the saved model is the mean of the parameters at every AVERAGE_EVERY-th step
    of the last fraction of the steps, never before densify_until; the last step's figures are
    logged beside it.  0: the last step's parameters, nothing logged."""
    import endowave_cl.train.average as average
    from endowave_cl.checkpoint import load_checkpoint
    from endowave_cl.gaussians import PARAM_NAMES, download
    monkeypatch.setattr(average, "AVERAGE_EVERY", 2)
    kw = dict(iterations=10, densify_from=1, densify_every=2, densify_until=6)
    for last, first in ((0.5, 7), (0.2, 8)):   # the window starts after densify_until / at 80 %
        tr = _trainer(scene, rt, tmp_path / str(last), average_last=last, **kw)
        snaps, hook = [], tr.average_step

        def record():
            hook()
            a = tr._average
            if a is not None and (tr.step == a.first or a.due(tr.step)):
                snaps.append((tr.step, download(tr.params)))
        tr.average_step = record
        m = tr.train(progress=False)
        assert [s for s, _ in snaps] == list(range(first, 11, 2))
        assert m["averaged"]["from_step"] == first and m["averaged"]["snapshots"] == len(snaps)
        assert set(m["averaged"]["last_step"]) >= {"psnr", "ssim"}
        saved = load_checkpoint(tr._run.last_saved)["gaussians"]
        for name in PARAM_NAMES:
            want = np.mean([getattr(g, name) for _, g in snaps], axis=0)
            np.testing.assert_allclose(getattr(saved, name), want, rtol=1e-5, atol=1e-6, err_msg=name)
        assert not np.array_equal(saved.means, snaps[-1][1].means)
    tr = _trainer(scene, rt, tmp_path / "off", average_last=0.0, **kw)
    assert "averaged" not in tr.train(progress=False)


def _adam_skip_culled(scene, rt, tmp_path):
    """adam_skip_culled: a Gaussian culled at the step's time (here: behind the camera) keeps its
    parameters and moments; without it, Adam moves it on the momentum of earlier steps."""
    k0, k1 = scene.train_indices[:2]
    out = {}
    for skip in (False, True):
        tr = _trainer(scene, rt, tmp_path / str(skip), adam_skip_culled=skip)
        tr.train_step(k0)                                    # every Gaussian gets moments
        means = tr.params["means"].get()
        means[0, 2] = -100.0                                 # Gaussian 0: culled from now on
        tr.params["means"].set(means)
        before = tr.params["means"].get()[0].copy()
        m_before = tr.adam.state_dict()["exp_avg"]["means"][0].copy()
        tr.train_step(k1)
        out[skip] = (before, tr.params["means"].get()[0], m_before, tr.adam.state_dict()["exp_avg"]["means"][0])
    b, a, mb, ma = out[True]
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(ma, mb)
    b, a, mb, ma = out[False]
    assert not np.array_equal(ma, mb)    # the moment decays (and the mean moves on it where it is not 0)


def _loss_effect(key, value, what):
    def check(scene, rt, tmp_path):
        what(_losses(rt, TrainConfig()), _losses(rt, TrainConfig(**{key: value})))
    return check


def _total_changes(part, delta):
    """The part is the same and the total changes by delta (new lambda - old lambda) x the part."""
    def what(b, n):
        assert n[part] == pytest.approx(b[part], rel=1e-6) and b[part] > 0
        assert n["total"] - b["total"] == pytest.approx(delta * b[part], rel=1e-5)
    return what


def _lambda_dssim(b, n):
    assert n["rgb"] == pytest.approx(0.5 * n["l1"] + 0.5 * (1 - n["ssim"]), rel=1e-6)
    d = TrainConfig().lambda_dssim        # the default's mix
    assert d != 0.5 and b["rgb"] == pytest.approx((1 - d) * b["l1"] + d * (1 - b["ssim"]), rel=1e-6)


def _flow_huber_delta(b, n):
    assert n["flow"] > b["flow"]          # inf: pure squared error, larger for errors beyond 4 px


def _dropped(part):
    def what(b, n):
        assert part in b and part not in n
    return what


def _wavelet_changes(b, n):
    assert n["wavelet"] != pytest.approx(b["wavelet"], rel=1e-4)
    assert n["l1"] == b["l1"]










def _between_s(scene, rt, tmp_path):
    """between_s: the drawn step's time is the pair's frame times mixed at the fraction that
    distribution gives from the same generator (triangular: the mean of two uniform draws); other
    names are refused by name."""
    from endowave_cl.errors import EndowaveError
    from endowave_cl.train.between import between_target, pair_time
    from endowave_cl.train.config import TrainConfig, validate_config
    times = {}
    for dist in ("uniform", "triangular"):
        tr = _trainer(scene, rt, tmp_path / dist, iterations=0, between_prob=1.0, between_s=dist)
        rng = np.random.default_rng(5)
        pair = tr._between.pairs[int(rng.integers(len(tr._between.pairs)))]
        u = float(rng.uniform(0.0, 1.0))
        s = u if dist == "uniform" else 0.5 * (u + float(rng.uniform(0.0, 1.0)))
        _, t, dev = tr._between.draw(np.random.default_rng(5))
        assert t == pytest.approx(pair_time(scene, pair, s), abs=1e-12)
        np.testing.assert_allclose(dev.image.get(), between_target(scene, pair, s, **_target_kw(tr))[0], atol=1e-6)
        times[dist] = t
    assert times["uniform"] != times["triangular"]
    with pytest.raises(EndowaveError, match="between_s"):
        validate_config(TrainConfig(between_s="middle"), "config.json")


def _between_levels(scene, rt, tmp_path):
    """between_levels: the drawn fraction moves onto the grid j / K, the target is between_target's
    at that fraction (float16-kept: within 5e-4), made once per pair and grid point; 1 is refused."""
    from endowave_cl.errors import EndowaveError
    from endowave_cl.train.between import between_target, level_fraction, pair_time
    from endowave_cl.train.config import TrainConfig, validate_config
    tr = _trainer(scene, rt, tmp_path / "k", iterations=0, between_prob=1.0, between_levels=4)
    rng = np.random.default_rng(5)
    pair = tr._between.pairs[int(rng.integers(len(tr._between.pairs)))]
    s = level_fraction(float(rng.uniform(0.0, 1.0)), 4)
    assert s in (0.25, 0.5, 0.75)
    _, t, dev = tr._between.draw(np.random.default_rng(5))
    assert t == pytest.approx(pair_time(scene, pair, s), abs=1e-12)
    want = between_target(scene, pair, s, **_target_kw(tr))[0]
    np.testing.assert_allclose(dev.image.get(), want, atol=5e-4)
    assert len(tr._between._static) == 1
    calls = []
    import endowave_cl.train.between as B
    real = B._flow_prediction
    B._flow_prediction = lambda *a, **k: calls.append(1) or real(*a, **k)
    try:
        _, _, dev2 = tr._between.draw(np.random.default_rng(5))     # the same pair and grid point: kept
    finally:
        B._flow_prediction = real
    assert not calls and np.array_equal(dev2.image.get(), dev.image.get())
    # 0: the continuous draw, nothing kept
    tr0 = _trainer(scene, rt, tmp_path / "c", iterations=0, between_prob=1.0)
    tr0._between.draw(np.random.default_rng(5))
    assert not tr0._between._static
    with pytest.raises(EndowaveError, match="between_levels"):
        validate_config(TrainConfig(between_levels=1), "config.json")


def _between_path(scene, rt, tmp_path):
    """between_path: "quadratic" bends the drawn target's paths with the pair's Bend (the flows to
    the training frames beyond a pair with a neighbour on both sides), which changes the target on
    the tiny scene's motion; "linear" draws the straight target; other names are refused by name."""
    from endowave_cl.errors import EndowaveError
    from endowave_cl.train.between import between_target, pair_bend
    from endowave_cl.train.config import TrainConfig, validate_config
    images = {}
    for path in ("linear", "quadratic"):
        tr = _trainer(scene, rt, tmp_path / path, iterations=0, between_prob=1.0, between_path=path)
        b = tr._between
        n = len(b.pairs)
        seed = next(x for x in range(100) if 0 < int(np.random.default_rng(x).integers(n)) < n - 1)
        rng = np.random.default_rng(seed)
        k = int(rng.integers(n))
        s = float(rng.uniform(0.0, 1.0))
        _, _, dev = b.draw(np.random.default_rng(seed))
        bend = None
        if path == "quadratic":
            fused = b._fused if tr.cfg.between_flow_splat else None
            bend = pair_bend(scene, b.pairs, k, lambda p: [p, *b.extra(p)], fused)
            assert bend.before[0] is not None and bend.after[0] is not None
        want = between_target(scene, b.pairs[k], s, bend=bend, **_target_kw(tr))[0]
        np.testing.assert_allclose(dev.image.get(), want, atol=1e-6)
        images[path] = dev.image.get()
    assert np.abs(images["linear"] - images["quadratic"]).max() > 1e-3
    with pytest.raises(EndowaveError, match="between_path"):
        validate_config(TrainConfig(between_path="cubic"), "config.json")


def _between_flows(scene, rt, tmp_path):
    """between_flows: the drawn in-between target fuses the listed estimators' flows of the pair
    with flow_method's; unknown methods are refused by name."""
    from endowave_cl.data.flow import flow_for_scene
    from endowave_cl.errors import EndowaveError
    from endowave_cl.train.between import between_target
    from endowave_cl.train.config import TrainConfig, validate_config
    tr = _trainer(scene, rt, tmp_path / "fused", iterations=0, between_prob=1.0,
                  between_flows="farneback, dis_fine")     # flow_method (dis_fine) itself is not repeated
    assert len(tr._between.extra_flows) == 1
    _, _, dev = tr._between.draw(np.random.default_rng(3))
    rng = np.random.default_rng(3)
    pair = tr._between.pairs[int(rng.integers(len(tr._between.pairs)))]
    s = float(rng.uniform(0.0, 1.0))
    other = dict(flow_for_scene(scene, method="farneback", progress=False))[pair.src]
    want = between_target(scene, pair, s, extra=[other], **_target_kw(tr))[0]
    alone = between_target(scene, pair, s, **_target_kw(tr))[0]
    np.testing.assert_allclose(dev.image.get(), want, atol=1e-6)
    assert not np.allclose(dev.image.get(), alone, atol=1e-4)
    with pytest.raises(EndowaveError, match="between_flows"):
        validate_config(TrainConfig(between_flows="dis,raft"), "cfg.toml")


def _between_fuse(scene, rt, tmp_path):
    """between_fuse: how the drawn in-between target combines between_flows' hypotheses ("mean":
    their plain average, "agree": weighed by their warps' agreement); other names are refused by
    key."""
    from endowave_cl.data.flow import flow_for_scene
    from endowave_cl.train.between import between_target
    from endowave_cl.train.config import validate_config
    for fuse, other_fuse in (("mean", "agree"), ("agree", "mean")):
        tr = _trainer(scene, rt, tmp_path / fuse, iterations=0, between_prob=1.0,   # the backward warps
                      between_flows="farneback", between_fuse=fuse, between_flow_splat=False)
        _, _, dev = tr._between.draw(np.random.default_rng(3))
        rng = np.random.default_rng(3)
        pair = tr._between.pairs[int(rng.integers(len(tr._between.pairs)))]
        s = float(rng.uniform(0.0, 1.0))
        other = dict(flow_for_scene(scene, method="farneback", progress=False))[pair.src]
        got = dev.image.get()
        np.testing.assert_allclose(got, between_target(scene, pair, s, extra=[other], **_target_kw(tr))[0], atol=1e-6)
        not_want = between_target(scene, pair, s, extra=[other], **_target_kw(tr, fuse=other_fuse))[0]
        assert not np.allclose(got, not_want, atol=1e-4)
        if fuse == "mean":
            one, ok1, _ = between_target(scene, pair, s, **_target_kw(tr))
            two, ok2, _ = between_target(scene, other, s, **_target_kw(tr))
            both = (ok1 > 0) & (ok2 > 0)       # where the tool hides one hypothesis, the other alone
            assert both.mean() > 0.5
            np.testing.assert_allclose(got[both], 0.5 * (one + two)[both], atol=1e-6)
    with pytest.raises(EndowaveError, match="between_fuse"):
        validate_config(TrainConfig(between_fuse="median"), "cfg.toml")


def _between_flow_splat(scene, rt, tmp_path):
    """between_flow_splat: the drawn in-between target pushes the frames forward along the flow
    hypotheses' consistent flows; off, it samples them backward."""
    from endowave_cl.train.between import between_target
    for on in (True, False):
        tr = _trainer(scene, rt, tmp_path / f"fs{on}", iterations=0, between_prob=1.0, between_flow_splat=on)
        _, _, dev = tr._between.draw(np.random.default_rng(3))
        rng = np.random.default_rng(3)
        pair = tr._between.pairs[int(rng.integers(len(tr._between.pairs)))]
        s = float(rng.uniform(0.0, 1.0))
        want, other = (between_target(scene, pair, s, **_target_kw(tr, flow_splat=f))[0] for f in (on, not on))
        np.testing.assert_allclose(dev.image.get(), want, atol=1e-6)
        assert not np.allclose(dev.image.get(), other, atol=1e-4)


def _drawn_with_model_motion(tr, rt, weight):
    """An in-between target drawn (seeded) with the model's rendered motion at this weight, and
    what it drew: (target image, pair, s, motion(camera, t, t_to))."""
    from endowave_cl.render import render

    def motion(camera, t, t_to):
        return tr.rendered_motion(render(rt, tr.params, camera, t, t_to))
    _, _, dev = tr._between.draw(np.random.default_rng(3), motion, weight)
    rng = np.random.default_rng(3)
    pair = tr._between.pairs[int(rng.integers(len(tr._between.pairs)))]
    return dev.image.get(), pair, float(rng.uniform(0.0, 1.0)), motion


def _between_model(scene, rt, tmp_path):
    """between_model: after densify_until the drawn in-between target blends in the pair's frames
    warped along the model's own rendered motion, with this weight; it is a weight in [0, 1]."""
    from endowave_cl.train.between import between_target
    from endowave_cl.train.config import validate_config
    tr = _trainer(scene, rt, tmp_path / "model", iterations=0, between_prob=1.0, densify_until=0,
                  between_model=0.5, between_model_splat=False)     # the splat: _between_model_splat
    got, pair, s, motion = _drawn_with_model_motion(tr, rt, 0.5)
    f0, f1 = scene.frames[pair.src], scene.frames[pair.dst]
    disp = motion(f0.camera, (1 - s) * f0.time + s * f1.time, f0.time)
    want = between_target(scene, pair, s, model_disp=disp, model_weight=0.5, **_target_kw(tr))[0]
    alone = between_target(scene, pair, s, **_target_kw(tr))[0]
    np.testing.assert_allclose(got, want, atol=1e-6)
    assert not np.allclose(got, alone, atol=1e-4)
    with pytest.raises(EndowaveError, match="between_model"):
        validate_config(TrainConfig(between_model=1.5), "cfg.toml")


def _between_model_splat(scene, rt, tmp_path):
    """between_model_splat: the model's part of the drawn in-between target splats the pair's frames
    forward along the motion the model renders at their own times; off, it warps them backward."""
    from endowave_cl.train.between import between_target
    for splat in (True, False):
        tr = _trainer(scene, rt, tmp_path / f"splat{splat}", iterations=0, between_prob=1.0, densify_until=0,
                      between_model=1.0, between_model_splat=splat)
        got, pair, s, motion = _drawn_with_model_motion(tr, rt, 1.0)
        f0, f1 = scene.frames[pair.src], scene.frames[pair.dst]
        t = (1 - s) * f0.time + s * f1.time
        kw = dict(model_disp=motion(f0.camera, t, f0.time), model_weight=1.0, **_target_kw(tr))
        splatted = between_target(scene, pair, s, model_fwd=(motion(f0.camera, f0.time, t),
                                                             motion(f1.camera, f1.time, t)), **kw)[0]
        backward = between_target(scene, pair, s, **kw)[0]
        want, other = (splatted, backward) if splat else (backward, splatted)
        np.testing.assert_allclose(got, want, atol=1e-6)
        assert not np.allclose(got, other, atol=1e-4)


def _between_motion_refresh(scene, rt, tmp_path):
    """between_motion_refresh: the model's motion at a pair's two frames is rendered over the whole
    pair, scaled to the step's fraction s and kept for that many steps; 0 renders it to s every time."""
    from endowave_cl.render import render
    from endowave_cl.train.between import between_target
    calls = []

    def motion(camera, t, t_to):
        calls.append((t, t_to))
        return tr.rendered_motion(render(rt, tr.params, camera, t, t_to))
    tr = _trainer(scene, rt, tmp_path / "refresh", iterations=0, between_prob=1.0, densify_until=0,
                  between_model=1.0, between_model_splat=True, between_motion_refresh=10)
    b = tr._between
    _, _, dev = b.draw(np.random.default_rng(3), motion, 1.0, step=5)
    rng = np.random.default_rng(3)
    index = int(rng.integers(len(b.pairs)))
    pair, s = b.pairs[index], float(rng.uniform(0.0, 1.0))
    f0, f1 = scene.frames[pair.src], scene.frames[pair.dst]
    t = (1 - s) * f0.time + s * f1.time
    assert calls[1:] == [(f0.time, f1.time), (f1.time, f0.time)]      # after the step's own render
    g0, g1 = motion(f0.camera, f0.time, f1.time), motion(f1.camera, f1.time, f0.time)
    want = between_target(scene, pair, s, model_disp=motion(f0.camera, t, f0.time), model_weight=1.0,
                          model_fwd=(np.float32(s) * g0, np.float32(1 - s) * g1), **_target_kw(tr))[0]
    np.testing.assert_allclose(dev.image.get(), want, atol=1e-6)
    del calls[:]
    b._pair_motion(index, motion, 14)          # kept: 9 steps old
    assert calls == []
    b._pair_motion(index, motion, 15)          # 10 steps old: rendered again
    assert calls == [(f0.time, f1.time), (f1.time, f0.time)]
    off = _trainer(scene, rt, tmp_path / "off", iterations=0, between_prob=1.0, densify_until=0,
                   between_model=1.0, between_model_splat=True, between_motion_refresh=0)
    del calls[:]
    tr = off
    off._between.draw(np.random.default_rng(3), motion, 1.0, step=5)
    assert calls[1:] == [(f0.time, t), (f1.time, t)]                   # rendered to s itself


CHECKS = {
    "iterations": _loop_effect("iterations", 4, _iterations),
    "minutes": _minutes,
    "seed": _seed,
    "deterministic": _deterministic,
    "log_every": _loop_effect("log_every", 2, _log_every),
    "eval_every": _loop_effect("eval_every", 2, _eval_every),
    "checkpoint_every": _loop_effect("checkpoint_every", 3, _checkpoint_every),
    "downscale": _downscale,
    "split": _split,
    "recipe": _recipe,
    "init_points": _init_points,
    "init_time_scale": _init_time_scale,
    "init_velocity": _init_velocity,
    "max_gaussians": _densify_effect(_max_gaussians),
    "flow_method": _flow_method,
    "flow_max_pixels": _flow_max_pixels,
    "sh_degree": _sh_degree,
    "temporal_freqs": _fixed("temporal_freqs", 2),
    "lr_position_init": _lr_position_init,
    "lr_position_final": _lr_position_final,
    "lr_position_steps": _lr_position_steps,
    "lr_time": _lr("lr_time", "means_t", 3e-4),
    "lr_features": _lr("lr_features", "sh", 1e-2),
    "lr_features_rest_divisor": _lr_features_rest_divisor,
    "lr_opacity": _lr("lr_opacity", "opacity", 0.02),
    "lr_scales": _lr("lr_scales", "scales", 0.01),
    "lr_scales_t": _lr("lr_scales_t", "scales_t", 0.02),
    "lr_rotation": _lr("lr_rotation", "quat_r", 0.003),
    "lr_phase": _lr("lr_phase", "phase", 0.01),
    "lr_anneal_final": _lr_anneal_final,
    "adam_skip_culled": _adam_skip_culled,
    "average_last": _average_last,
    "densify_from": _loop_effect("densify_from", 3, _densify_from),
    "densify_every": _loop_effect("densify_every", 3, _densify_every),
    "densify_until": _loop_effect("densify_until", 6, _densify_until),
    "densify_grad_threshold": _densify_effect(_densify_grad_threshold),
    "percent_dense": _densify_effect(_percent_dense),
    "split_children": _densify_effect(_split_children),
    "split_scale_divisor": _densify_effect(_split_scale_divisor),
    "cap_turnover": _densify_effect(_cap_turnover),
    "prune_opacity": _densify_effect(_prune_opacity),
    "prune_screen_size": _densify_effect(_prune_screen_size),
    "prune_world_size": _densify_effect(_prune_world_size),
    "opacity_reset_every": _loop_effect("opacity_reset_every", 2, _opacity_reset_every),
    "opacity_reset_value": _opacity_reset_value,
    "lambda_rgb": _loss_effect("lambda_rgb", 2.0, _total_changes("rgb", 1.0)),
    "lambda_dssim": _loss_effect("lambda_dssim", 0.5, _lambda_dssim),
    "lambda_depth": _loss_effect("lambda_depth", 3.0, _total_changes("depth", 2.9)),
    "lambda_flow": _loss_effect("lambda_flow", 0.5, _total_changes("flow", 0.49)),
    "flow_huber_delta": _loss_effect("flow_huber_delta", math.inf, _flow_huber_delta),
    "between_prob": _between_prob,
    "between_anneal_final": _between_anneal_final,
    "between_s": _between_s,
    "between_path": _between_path,
    "between_levels": _between_levels,
    "between_flows": _between_flows,
    "between_model": _between_model,
    "between_fuse": _between_fuse,
    "between_model_splat": _between_model_splat,
    "between_flow_splat": _between_flow_splat,
    "between_motion_refresh": _between_motion_refresh,
    "lambda_wavelet": _loss_effect("lambda_wavelet", 3.0, _total_changes("wavelet", 2.0)),
    "use_depth": _loss_effect("use_depth", False, _dropped("depth")),
    "use_flow": _loss_effect("use_flow", False, _dropped("flow")),
    "use_wavelet": _loss_effect("use_wavelet", False, _dropped("wavelet")),
    "wavelet_q": _loss_effect("wavelet_q", 1, _wavelet_changes),
    "wavelet_levels": _loss_effect("wavelet_levels", 1, _wavelet_changes),
    "wavelet_weight_ll": _loss_effect("wavelet_weight_ll", 8.0, _wavelet_changes),
    "wavelet_weight_lh": _loss_effect("wavelet_weight_lh", 8.0, _wavelet_changes),
    "wavelet_weight_hl": _loss_effect("wavelet_weight_hl", 8.0, _wavelet_changes),
    "wavelet_weight_hh": _loss_effect("wavelet_weight_hh", 8.0, _wavelet_changes),
}


def test_every_key_has_a_check():
    assert set(CHECKS) == set(KEYS)


@pytest.mark.parametrize("key", sorted(CHECKS))
def test_key_changes_what_it_claims(key, scene, rt, tmp_path, monkeypatch):
    check = CHECKS[key]
    if "monkeypatch" in check.__code__.co_varnames[:check.__code__.co_argcount]:
        check(scene, rt, tmp_path, monkeypatch)
    else:
        check(scene, rt, tmp_path)


def test_trainer_passes_the_wavelet_keys_to_the_loss(scene, rt, tmp_path):
    tr = _trainer(scene, rt, tmp_path, wavelet_q=1, wavelet_levels=3, wavelet_weight_ll=1.0,
                  wavelet_weight_lh=2.0, wavelet_weight_hl=3.0, wavelet_weight_hh=4.0)
    w = tr.wavelet_config
    assert (w.q, w.levels, w.weights) == (1, 3, (1.0, 2.0, 3.0, 4.0))


def test_opacity_reset_keeps_statistics_and_other_moments(scene, rt, tmp_path):
    """Trainer.reset_opacity caps the opacity and zeroes its moments only: the other parameters and
    moments and the densification statistics are what they were."""
    from endowave_cl.gaussians import PARAM_NAMES
    tr = _trainer(scene, rt, tmp_path, opacity_reset_value=0.05)
    for k in tr.scene.train_indices[:2]:
        tr.train_step(k)
    params = {n: tr.params[n].get() for n in PARAM_NAMES}
    state = tr.adam.state_dict()
    stats = {n: a.get() for n, a in tr.stats.items()}
    assert stats["count"].max() > 0 and np.abs(state["exp_avg"]["opacity"]).max() > 0
    tr.reset_opacity()
    after = tr.adam.state_dict()
    for n in PARAM_NAMES:
        if n != "opacity":
            np.testing.assert_array_equal(tr.params[n].get(), params[n])
            np.testing.assert_array_equal(after["exp_avg"][n], state["exp_avg"][n])
            np.testing.assert_array_equal(after["exp_avg_sq"][n], state["exp_avg_sq"][n])
    np.testing.assert_array_equal(tr.params["opacity"].get(), np.minimum(params["opacity"], np.float32(logit(0.05))))
    assert not after["exp_avg"]["opacity"].any() and not after["exp_avg_sq"]["opacity"].any()
    for n, a in stats.items():
        np.testing.assert_array_equal(tr.stats[n].get(), a)


def test_removed_keys_are_refused_as_settings_and_ignored_in_saved_runs(scene, tmp_path, capsys):
    """A key removed with its code (config.py REMOVED) is refused by --set, a TOML file and a batch
    manifest's settings, naming the finding; a saved run's config.json that names it still opens,
    with a note where the run had it on."""
    from endowave_cl.checkpoint import checkpoint_path, save_checkpoint
    from endowave_cl.run_io import load_run
    from endowave_cl.train.config import REMOVED
    assert not set(REMOVED) & set(KEYS)
    with pytest.raises(EndowaveError, match=r"^override: key 'between_two_flow' was removed .*finding 9"):
        load_config(None, {"between_two_flow": "true"})
    toml = tmp_path / "old.toml"
    toml.write_text("flow_anneal_final = 0.5\n")
    with pytest.raises(EndowaveError, match=r"old.toml: key 'flow_anneal_final' was removed .*finding 17"):
        load_config(str(toml))
    with pytest.raises(EndowaveError, match="key 'lambda_flow_gaussian' was removed"):
        TrainConfig.from_dict({"lambda_flow_gaussian": 0.0})
    with pytest.raises(EndowaveError, match=r"^override: key 'between_push' was removed .*'fused', now the only "
                                            r"behaviour.*finding 22"):
        load_config(None, {"between_push": "fused"})
    for name, on in (("off", {k: off for k, (off, _) in REMOVED.items()}),
                     ("on", {"between_by_time": True, "flow_photo_max": 0.03, "between_splat": "colour",
                             "between_sampler": "linear"})):
        d = tmp_path / name
        d.mkdir()
        cfg = TrainConfig(iterations=7)
        (d / "config.json").write_text(json.dumps({**cfg.to_dict(), **on, "scene": str(scene.path)}))
        save_checkpoint(checkpoint_path(d, 1), Gaussians.random(3), None, 1, {**cfg.to_dict(), **on})
        capsys.readouterr()
        assert load_run(d).cfg == cfg
        notes = capsys.readouterr().err
        if name == "off":
            assert "removed" not in notes
        else:
            assert "between_by_time = True ignored: key 'between_by_time' was removed" in notes
            assert "flow_photo_max = 0.03 ignored" in notes and "flow_anneal_final" not in notes
            assert "between_splat = 'colour' ignored: key 'between_splat' was removed" in notes
            assert "finding 21" in notes and "between_sampler = 'linear' ignored" in notes
            assert "between_push" not in notes


def test_config_is_frozen_and_resolution_gives_a_new_one(scene, rt, tmp_path):
    """A TrainConfig cannot be changed in place; the trainer's resolved config is a new one and the
    caller's is as it was (iterations, density and SH degree still 0 / -1)."""
    import dataclasses
    cfg = tiny_config(**{**QUICK, "iterations": 0, "max_gaussians": 0, "sh_degree": -1})
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.iterations = 5
    before = cfg.to_dict()
    from endowave_cl.train.trainer import Trainer
    tr = Trainer(scene, cfg, tmp_path / "run", rt, log=lambda s: None, resume=False)
    assert cfg.to_dict() == before
    assert tr.cfg is not cfg and tr.cfg.iterations > 0 and tr.cfg.max_gaussians > 0 and tr.cfg.sh_degree >= 0


def test_sections_and_flat_keys_are_one_setting():
    """Each flat key is one section's field (FLAT, from SECTIONS): reading, building and replacing
    by either name reach the same value; to_dict gives the flat keys, and from_dict takes them back."""
    import pickle
    from endowave_cl.train.config import FLAT, SECTIONS
    cfg = TrainConfig(between_prob=0.3, lr_time=1e-3, wavelet_q=3, flow_method="dis")
    assert (cfg.between.prob, cfg.optim.lr_time, cfg.wavelet.q, cfg.flow.method) == (0.3, 1e-3, 3, "dis")
    assert (cfg.between_prob, cfg.lr_time, cfg.wavelet_q, cfg.flow_method) == (0.3, 1e-3, 3, "dis")
    assert cfg.replace(between=cfg.between.__class__(prob=0.1)).between_prob == 0.1
    assert cfg.replace(between_prob=0.2).between.prob == 0.2 and cfg.between.prob == 0.3
    assert sorted(FLAT) == sorted(k for k in KEYS if k != "recipe")
    assert {name for name, _ in FLAT.values()} == set(SECTIONS)
    for key, (name, field_name) in FLAT.items():
        assert getattr(getattr(TrainConfig(), name), field_name) == getattr(TrainConfig(), key)
    assert list(cfg.to_dict()) == list(KEYS)
    assert TrainConfig.from_dict(cfg.to_dict()) == cfg == pickle.loads(pickle.dumps(cfg))
    with pytest.raises(TypeError, match="unknown key 'between_probability'"):
        TrainConfig(between_probability=0.3)
    with pytest.raises(AttributeError):
        cfg.between_probability
