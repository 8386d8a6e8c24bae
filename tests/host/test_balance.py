"""train/balance.py: the steps' weights of frame_balance."""
from __future__ import annotations

import math

import pytest

from endowave_cl.train.balance import MAX_WEIGHT, FrameBalance


def test_disabled_weighs_every_step_one():
    b = FrameBalance(0.0)
    for loss in (0.01, 0.1, 0.001):
        assert b.weight("plain", loss) == 1.0
        b.update("plain", loss)
    assert not b.enabled


def test_first_step_of_a_kind_is_one_then_relative_to_the_geometric_mean():
    b = FrameBalance(1.0, memory=0.0)        # memory 0: G is the last loss of the kind
    assert b.weight("plain", 0.02) == 1.0
    b.update("plain", 0.02)
    assert b.weight("plain", 0.01) == pytest.approx(2.0)     # half the loss: twice the weight
    assert b.weight("plain", 0.04) == pytest.approx(0.5)
    assert b.weight("between", 0.01) == 1.0                  # the kinds are apart


def test_power_and_clip():
    b = FrameBalance(0.5, memory=0.0)
    b.update("plain", 0.04)
    assert b.weight("plain", 0.01) == pytest.approx(2.0)     # (0.04 / 0.01) ** 0.5
    assert b.weight("plain", 1e-9) == MAX_WEIGHT
    assert b.weight("plain", 1e3) == 1.0 / MAX_WEIGHT


def test_running_geometric_mean():
    b = FrameBalance(1.0, memory=0.5)
    b.update("plain", 0.01)
    b.update("plain", 0.04)                  # log G = (log 0.01 + log 0.04) / 2: G = 0.02
    assert math.exp(b.log_mean["plain"]) == pytest.approx(0.02)
    assert b.weight("plain", 0.02) == pytest.approx(1.0)


@pytest.mark.parametrize("loss", [0.0, -1.0, float("nan"), float("inf")])
def test_bad_losses_are_skipped(loss):
    b = FrameBalance(1.0)
    b.update("plain", loss)
    assert "plain" not in b.log_mean
    b.update("plain", 0.02)
    assert b.weight("plain", loss) == 1.0


def test_power_must_be_finite_non_negative():
    with pytest.raises(ValueError, match="frame_balance"):
        FrameBalance(-1.0)
