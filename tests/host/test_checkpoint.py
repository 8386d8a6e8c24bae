"""Training config (TOML loading, dict round trip) and checkpoints."""
from __future__ import annotations

import pytest

from endowave_cl.errors import EndowaveError
from endowave_cl.train.config import (DENSIFY_GRAD_THRESHOLD, TrainConfig, densify_threshold_for, load_config,
                                      recipe_config)


def test_config_defaults_follow_design():
    c = TrainConfig()
    # the position rates are 4x DESIGN.md's (3DGS's) 1.6e-4 / 1.6e-6 (research/QUALITY.md finding 15)
    assert (c.lr_position_init, c.lr_position_final, c.lr_features, c.lr_opacity, c.lr_scales,
            c.lr_rotation) == (6.4e-4, 6.4e-6, 2.5e-3, 0.05, 5e-3, 1e-3)
    assert (c.densify_from, c.densify_every, c.densify_grad_threshold, c.prune_opacity,
            c.opacity_reset_every) == (500, 100, 0.0, 0.005, 3000)
    # 0: 1.4e-4 up to 320x256, scaled by sqrt(320x256 / pixels) above (research/QUALITY.md findings 27, 42)
    assert DENSIFY_GRAD_THRESHOLD == 1.4e-4
    assert densify_threshold_for(160, 128) == densify_threshold_for(320, 256) == 1.4e-4
    assert densify_threshold_for(640, 512) == pytest.approx(7e-5, rel=1e-12)
    assert densify_threshold_for(1280, 1024) == pytest.approx(3.5e-5, rel=1e-12)
    c = c.resolve_density(640, 512)
    assert c.densify_grad_threshold == pytest.approx(7e-5, rel=1e-12)
    c = c.resolve_density(320, 256)                # resolved once: a given threshold stays
    assert c.densify_grad_threshold == pytest.approx(7e-5, rel=1e-12)
    # the depth loss's weight is a tenth of DESIGN.md's, in scene units (finding 18); D-SSIM 0.4
    # (finding 44), 3DGS's 0.2 in the paper's recipe
    assert (c.lambda_rgb, c.lambda_dssim, c.lambda_depth) == (1.0, 0.4, 0.1)
    assert recipe_config("paper").lambda_dssim == 0.2
    # the saved model averages the last tenth of the steps (finding 51); the paper's is its last step
    assert TrainConfig().average_last == 0.1 and recipe_config("paper").average_last == 0.0


def test_load_config_toml_and_overrides(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text("iterations = 200\nlr_opacity = 1\nuse_flow = false\n[train]\nseed = 7\n")
    c = load_config(str(p), {"flow_method": "deepflow", "lambda_flow": "0.5", "use_depth": "false", "iterations": "300"})
    assert c.iterations == 300 and c.lr_opacity == 1.0 and isinstance(c.lr_opacity, float)
    assert c.use_flow is False and c.use_depth is False and c.seed == 7 and c.lambda_flow == 0.5
    assert c.flow_method == "deepflow"
    assert load_config(None, {}) == TrainConfig()


@pytest.mark.parametrize("text,key", [("itrations = 3\n", "itrations"), ("iterations = 2.5\n", "iterations"),
                                      ("use_depth = 1\n", "use_depth"), ("lr_opacity = 'a'\n", "lr_opacity"),
                                      ("iterations = -1\n", "iterations"),
                                      ("flow_method = 3\n", "flow_method")])
def test_load_config_bad_keys_name_file_and_key(tmp_path, text, key):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(EndowaveError, match=rf"bad\.toml.*'{key}'"):
        load_config(str(p), {})


def test_load_config_bad_toml_and_missing_file(tmp_path):
    p = tmp_path / "broken.toml"
    p.write_text("iterations = = 3\n")
    with pytest.raises(EndowaveError, match="broken.toml: not valid TOML"):
        load_config(str(p), {})
    with pytest.raises(EndowaveError, match="does not exist"):
        load_config(str(tmp_path / "nope.toml"), {})
    with pytest.raises(EndowaveError, match="override: key 'seed'"):
        load_config(None, {"seed": "x"})
    assert load_config(None, {"flow_huber_delta": "inf"}).flow_huber_delta == float("inf")
    with pytest.raises(EndowaveError, match="flow_huber_delta' must be > 0"):
        load_config(None, {"flow_huber_delta": "0"})


def test_config_dict_round_trip():
    c = TrainConfig(iterations=77, use_wavelet=False, lambda_flow=0.3)
    d = c.to_dict()
    assert TrainConfig.from_dict(d) == c
    with pytest.raises(EndowaveError, match="unknown key 'bogus'"):
        TrainConfig.from_dict({**d, "bogus": 1})


# -- checkpoints ---------------------------------------------------------------------------------
import numpy as np  # noqa: E402

from endowave_cl.gaussians import PARAM_NAMES, Gaussians  # noqa: E402
from endowave_cl.checkpoint import (checkpoint_path, latest_checkpoint, load_checkpoint,  # noqa: E402
                                          save_checkpoint)


def _adam_state(g, seed=0):
    rng = np.random.default_rng(seed)
    return {"step": 12,
            "exp_avg": {n: rng.standard_normal(a.shape).astype(np.float32) for n, a in g.as_dict().items()},
            "exp_avg_sq": {n: rng.random(a.shape).astype(np.float32) for n, a in g.as_dict().items()}}


def test_checkpoint_round_trip(tmp_path):
    g = Gaussians.random(9, seed=1)
    st = _adam_state(g)
    cfg = TrainConfig(iterations=55).to_dict()
    p = save_checkpoint(checkpoint_path(tmp_path, 40), g, st, 40, cfg,
                        {"extent": 2.5, "scene": "x/y", "grad_accum": np.arange(9, dtype=np.float32)})
    assert p.name == "checkpoint_0000040.npz"
    ck = load_checkpoint(p)
    assert ck["step"] == 40 and ck["adam_state"]["step"] == 12
    for n in PARAM_NAMES:
        np.testing.assert_array_equal(getattr(ck["gaussians"], n), getattr(g, n))
        np.testing.assert_array_equal(ck["adam_state"]["exp_avg"][n], st["exp_avg"][n])
        np.testing.assert_array_equal(ck["adam_state"]["exp_avg_sq"][n], st["exp_avg_sq"][n])
    assert TrainConfig.from_dict(ck["config"]) == TrainConfig(iterations=55)
    assert ck["extra"]["extent"] == 2.5 and ck["extra"]["scene"] == "x/y"
    np.testing.assert_array_equal(ck["extra"]["grad_accum"], np.arange(9))
    # no Adam state, empty scene
    p2 = save_checkpoint(tmp_path / "e.npz", Gaussians.empty(), None, 0, cfg, None)
    ck2 = load_checkpoint(p2)
    assert ck2["adam_state"] is None and len(ck2["gaussians"]) == 0 and ck2["extra"] == {}


def test_latest_checkpoint(tmp_path):
    assert latest_checkpoint(tmp_path) is None
    assert latest_checkpoint(tmp_path / "missing") is None
    g = Gaussians.random(2)
    for s in (100, 2000, 300):
        save_checkpoint(checkpoint_path(tmp_path, s), g, None, s, {}, {})
    (tmp_path / "checkpoint_0009999.npz.abc.tmp").write_bytes(b"partial")
    assert latest_checkpoint(tmp_path).name == "checkpoint_0002000.npz"


def test_truncated_or_corrupt_checkpoint_gives_clear_error(tmp_path):
    g = Gaussians.random(50)
    p = save_checkpoint(tmp_path / "c.npz", g, _adam_state(g), 3, {}, {})
    data = p.read_bytes()
    for i, bad in enumerate([data[: len(data) // 2], data[:100], b"", b"not a zip file at all"]):
        q = tmp_path / f"bad{i}.npz"
        q.write_bytes(bad)
        with pytest.raises(EndowaveError, match=rf"bad{i}\.npz: not a readable checkpoint"):
            load_checkpoint(q)
    # flip bytes inside the stored data: the zip CRC check catches it
    flipped = bytearray(data)
    mid = len(flipped) // 2
    flipped[mid:mid + 16] = bytes(255 - b for b in flipped[mid:mid + 16])
    q = tmp_path / "flipped.npz"
    q.write_bytes(bytes(flipped))
    with pytest.raises(EndowaveError, match=r"flipped\.npz"):
        load_checkpoint(q)
    with pytest.raises(EndowaveError, match="does not exist"):
        load_checkpoint(tmp_path / "none.npz")


def test_inconsistent_checkpoint_names_the_entry(tmp_path):
    q = tmp_path / "other.npz"
    np.savez(q, a=np.zeros(3))
    with pytest.raises(EndowaveError, match=r"other\.npz: checkpoint has no entry 'format'"):
        load_checkpoint(q)
    g = Gaussians.random(4)
    p = save_checkpoint(tmp_path / "s.npz", g, None, 1, {}, {})
    with np.load(p) as z:
        d = {k: z[k] for k in z.files}
    d["param/opacity"] = np.zeros(3, np.float32)
    np.savez(tmp_path / "shape.npz", **d)
    with pytest.raises(EndowaveError, match=r"shape\.npz: param/opacity has shape \(3,\)"):
        load_checkpoint(tmp_path / "shape.npz")


def test_checkpoint_of_another_format_is_refused_with_the_reason(tmp_path):
    """A format-1 checkpoint (fitted to the 3DGS low-pass 0.3) would render differently with this
    version's LOWPASS: refused in one line that names the file and why; an unknown format too."""
    g = Gaussians.random(4)
    p = save_checkpoint(tmp_path / "s.npz", g, None, 1, {}, {})
    with np.load(p) as z:
        d = {k: z[k] for k in z.files}
    for fmt, why in ((1, "low-pass of 0.3"), (99, "")):
        d["format"] = np.array(fmt)
        np.savez(tmp_path / f"f{fmt}.npz", **d)
        with pytest.raises(EndowaveError, match=rf"f{fmt}\.npz: checkpoint format {fmt}, this version reads 2") as e:
            load_checkpoint(tmp_path / f"f{fmt}.npz")
        assert why in str(e.value) and "\n" not in str(e.value)


def test_failed_write_keeps_the_previous_checkpoint(tmp_path, monkeypatch):
    g = Gaussians.random(5, seed=2)
    p = save_checkpoint(tmp_path / "checkpoint_0000001.npz", g, None, 1, {}, {})
    before = p.read_bytes()

    def boom(f, **arrays):  # writes part of the file, then fails
        f.write(b"PK\x03\x04 partial data")
        raise RuntimeError("disk full")
    monkeypatch.setattr(np, "savez", boom)
    with pytest.raises(RuntimeError, match="disk full"):
        save_checkpoint(p, Gaussians.random(7), None, 2, {}, {})
    assert p.read_bytes() == before
    assert [x.name for x in tmp_path.iterdir()] == [p.name]  # no temporary file left behind
    monkeypatch.undo()
    assert load_checkpoint(p)["step"] == 1
    with pytest.raises(EndowaveError, match="cannot save extra"):
        save_checkpoint(p, g, None, 3, {}, {"bad": object()})
    assert p.read_bytes() == before
