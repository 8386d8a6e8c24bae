"""The training loop that reads each step's outcome one step late (train/trainer.py module
docstring): the same updates, to the bit, as the loop that waits at every step, also where steps
overflow their buffers and are done again; a non-finite step is caught and not applied."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import tiny_config

pytestmark = pytest.mark.slow


def _cfg(**kw):
    # deterministic: the adjoint's sums in a fixed order, so that two runs can agree to the bit
    return tiny_config(**{**dict(iterations=60, init_points=2000, densify_from=20, densify_every=20,
                                 densify_until=40, log_every=25, deterministic=True,
                                 between_prob=0.5), **kw})


def _train(rt, scene, run, monkeypatch, blocking: bool, **kw):
    from endowave_cl.train import trainer as trainer_mod
    monkeypatch.setenv(trainer_mod.ENV_BLOCKING_STEPS, "1" if blocking else "0")
    tr = trainer_mod.Trainer(scene, _cfg(**kw), run, rt, log=lambda s: None)
    redone, settled = [], []
    rewind, settle = tr._rewind, tr._settle
    tr._rewind = lambda state: (redone.append(state.step), rewind(state))[1]
    tr._settle = lambda p: (settled.append(p.step), settle(p))[1]
    kinds, schedule = [], tr.schedule_step
    tr.schedule_step = lambda order: (lambda r: (kinds.append(r[0]), r)[1])(schedule(order))
    tr.train(progress=False)
    assert bool(settled) != blocking      # the deferred loop read its steps late, the other did not
    assert "between" in kinds and "plain" in kinds, kinds
    return tr, redone


def _assert_same_state(a, b):
    from endowave_cl.gaussians import download
    ga, gb = download(a.params), download(b.params)
    for name in ("means", "scales", "quat_l", "quat_r", "opacity", "sh", "phase"):
        np.testing.assert_array_equal(getattr(ga, name), getattr(gb, name), err_msg=name)
    sa, sb = a.adam.state_dict(), b.adam.state_dict()
    assert sa["step"] == sb["step"]
    for key in ("exp_avg", "exp_avg_sq"):
        for name in sa[key]:
            np.testing.assert_array_equal(sa[key][name], sb[key][name], err_msg=f"{key} {name}")
    assert [h["total"] for h in a.history] == [h["total"] for h in b.history]


@pytest.mark.parametrize("targets", ["host", "device"])
def test_deferred_loop_matches_the_blocking_loop(rt, tiny_scene, tmp_path, monkeypatch, targets):
    """In-between targets built on the host or on the device (the supervised count then stays on
    the device and enters the gate); the steps after densify_until blend in the model's motion."""
    from endowave_cl.data.scene import load_scene
    monkeypatch.setenv("ENDOWAVE_BETWEEN_TARGET", targets)
    scene = load_scene(tiny_scene)
    ref, _ = _train(rt, scene, tmp_path / "blocking", monkeypatch, blocking=True)
    got, redone = _train(rt, scene, tmp_path / "deferred", monkeypatch, blocking=False)
    assert got.step == ref.step == 60
    _assert_same_state(got, ref)


def test_overflowed_steps_are_done_again_to_the_same_bits(rt, tiny_scene, tmp_path, monkeypatch):
    """With no headroom in the pair and row buffers a step overflows whenever it needs more than
    the one before: the deferred loop finds it skipped on the device and does it again."""
    from endowave_cl.data.scene import load_scene
    from endowave_cl.ops import binning, select
    monkeypatch.setattr(binning, "HEADROOM", 1.0)
    monkeypatch.setattr(binning, "MIN_CAPACITY", 1)
    monkeypatch.setattr(select, "HEADROOM", 1.0)
    monkeypatch.setattr(select, "MIN_ROWS", 1)
    scene = load_scene(tiny_scene)
    ref, _ = _train(rt, scene, tmp_path / "blocking", monkeypatch, blocking=True)
    got, redone = _train(rt, scene, tmp_path / "deferred", monkeypatch, blocking=False)
    assert redone and got.redone_steps == len(redone), "no step overflowed: the test does not test the redo"
    _assert_same_state(got, ref)


def test_a_deferred_nan_step_is_caught_and_not_applied(rt, tiny_scene, tmp_path, monkeypatch):
    from endowave_cl.data.scene import load_scene
    from endowave_cl.gaussians import download
    from endowave_cl.train import trainer as trainer_mod
    monkeypatch.setenv(trainer_mod.ENV_BLOCKING_STEPS, "0")
    scene = load_scene(tiny_scene)
    tr = trainer_mod.Trainer(scene, _cfg(between_prob=0.0, use_flow=False), tmp_path / "run", rt,
                             log=lambda s: None)
    for k in scene.train_indices:                 # a NaN in every frame makes the first step's loss NaN
        img = tr.targets[k].dev.image
        host = img.get()
        host[5, 7, 1] = float("nan")
        img.set(host)
    before = download(tr.params)
    with pytest.raises(trainer_mod.TrainingDiverged, match=r"step 0 .*non-finite"):
        tr.train(progress=False)
    after = download(tr.params)
    np.testing.assert_array_equal(after.means, before.means)   # neither it nor the step behind it applied
    np.testing.assert_array_equal(after.sh, before.sh)


def test_deferred_steps_read_nothing_in_steady_state(rt, tiny_scene, tmp_path, monkeypatch):
    """Between log steps the loop's steps (plain ones and in-between ones before densify_until)
    make no blocking read and wait for no count: their outcome is read behind the next step."""
    import pyopencl as cl

    from endowave_cl.data.scene import load_scene
    from endowave_cl.ops.binning import PairCount
    from endowave_cl.train import trainer as trainer_mod
    monkeypatch.setenv(trainer_mod.ENV_BLOCKING_STEPS, "0")
    monkeypatch.setenv("ENDOWAVE_BETWEEN_TARGET", "host")
    scene = load_scene(tiny_scene)
    tr = trainer_mod.Trainer(scene, _cfg(iterations=40, log_every=20, densify_from=1000, densify_until=1000),
                             tmp_path / "run", rt, log=lambda s: None)
    counts = {"reads": 0, "waits": 0}
    plain_copy, plain_value = cl.enqueue_copy, PairCount.value

    def copy(queue, dest, src, **kw):
        counts["reads"] += int(isinstance(dest, np.ndarray) and kw.get("is_blocking", True))
        return plain_copy(queue, dest, src, **kw)

    def value(pc):
        counts["waits"] += int(pc.pending)
        return plain_value(pc)
    monkeypatch.setattr(cl, "enqueue_copy", copy)
    monkeypatch.setattr(PairCount, "value", value)
    per_step, schedule = [], tr.schedule_step

    def step(order):
        before = dict(counts)
        kind, result = schedule(order)
        per_step.append((tr._defer, kind, counts["reads"] - before["reads"], counts["waits"] - before["waits"]))
        return kind, result
    tr.schedule_step = step
    tr.train(progress=False)
    deferred = [(kind, reads, waits) for defer, kind, reads, waits in per_step[3:] if defer]
    assert len(deferred) >= 30 and {kind for kind, _, _ in deferred} == {"plain", "between"}
    assert all(reads == 0 and waits == 0 for _, reads, waits in deferred), deferred
