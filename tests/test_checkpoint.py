"""Training config (TOML loading, dict round trip) and checkpoints."""
from __future__ import annotations

import pytest

from endowave_cl.errors import EndowaveError
from endowave_cl.train.config import TrainConfig, load_config


def test_config_defaults_follow_design():
    c = TrainConfig()
    assert (c.lr_position_init, c.lr_position_final, c.lr_features, c.lr_opacity, c.lr_scales,
            c.lr_rotation) == (1.6e-4, 1.6e-6, 2.5e-3, 0.05, 5e-3, 1e-3)
    assert (c.densify_from, c.densify_every, c.densify_grad_threshold, c.prune_opacity,
            c.opacity_reset_every) == (500, 100, 2e-4, 0.005, 3000)
    assert (c.lambda_rgb, c.lambda_dssim, c.lambda_depth) == (1.0, 0.2, 1.0)


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
                                      ("iterations = 0\n", "iterations"),
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


def test_config_dict_round_trip():
    c = TrainConfig(iterations=77, use_wavelet=False, lambda_flow=0.3)
    d = c.to_dict()
    assert TrainConfig.from_dict(d) == c
    with pytest.raises(EndowaveError, match="unknown key 'bogus'"):
        TrainConfig.from_dict({**d, "bogus": 1})
