"""--minutes: a schedule planned from the measured step rate, ending within the budget."""
from __future__ import annotations

import time

import pytest

from endowave_cl.train.budget import BudgetPlan
from endowave_cl.train.config import TrainConfig


def test_replan_scales_the_schedule_shape():
    cfg = TrainConfig(iterations=3000, densify_from=500, densify_until=2000, opacity_reset_every=3000)
    plan = BudgetPlan.start(cfg, minutes=1.0, reserve=0.0)
    planned = plan.replan(cfg, step=0, seconds_per_step=0.1)   # 60 s at 0.1 s: 600 steps, 80% while densifying
    total = plan.planned
    assert total == pytest.approx(480, abs=2)
    assert cfg.iterations == 3000                                # a new config; the given one is as it was
    cfg = planned
    assert cfg.iterations == total
    r = total / 3000
    assert cfg.densify_from == round(500 * r) and cfg.densify_until == round(2000 * r)
    assert cfg.lr_position_steps == round(3000 * r)
    assert not plan.out_of_time()


def test_replan_keeps_a_scaled_key_that_is_off():
    """A schedule key at 0 (off) stays 0; a positive one scales with the plan."""
    for refresh in (0, 500):
        cfg = TrainConfig(iterations=3000, between_motion_refresh=refresh)
        plan = BudgetPlan.start(cfg, minutes=1.0, reserve=0.0)
        cfg = plan.replan(cfg, step=0, seconds_per_step=0.1)
        total = plan.planned
        assert cfg.between_motion_refresh == (round(refresh * total / 3000) if refresh else 0)


@pytest.mark.slow
def test_minutes_stops_within_budget(rt, tmp_path):
    from endowave_cl.data.scene import load_scene
    from endowave_cl.data.synth import make_synthetic_scene
    from endowave_cl.train.trainer import Trainer
    scene = load_scene(make_synthetic_scene(tmp_path / "s", width=48, height=32, frames=8, seed=1))
    # kernel builds on a cold cache would spend the budget: build them first
    Trainer(scene, TrainConfig(iterations=2, init_points=500, eval_every=0, checkpoint_every=0, use_flow=False),
            tmp_path / "warm", rt, log=lambda s: None).train(progress=False)
    minutes = 0.25
    cfg = TrainConfig(iterations=100000, minutes=minutes, init_points=1500, eval_every=0, checkpoint_every=0,
                      log_every=10, use_flow=False)
    t0 = time.perf_counter()
    msgs = []
    tr = Trainer(scene, cfg, tmp_path / "run", rt, log=msgs.append)
    m = tr.train(progress=False)
    took = time.perf_counter() - t0
    print(f"{m['step']} steps planned {tr.cfg.iterations}, {took:.1f} s of {60 * minutes:.0f}")
    # the loop stops inside the budget (one step of slack); the final save and evaluation come
    # after it, and take longer on a loaded machine
    assert m["train_seconds"] <= 60 * minutes * 1.05
    assert took <= 60 * minutes * 1.5
    assert m["step"] > 20 and tr.cfg.iterations < 100000    # it trained and the plan replaced 100000
