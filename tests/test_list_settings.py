"""`endowave-cl train --list-settings` names every TrainConfig key with its default, range and a
one-line meaning; a mistyped key in --set or a TOML file gets a "did you mean" (issue 59)."""
from __future__ import annotations

from dataclasses import fields

import pytest

from endowave_cl.cli import main as cli_main
from endowave_cl.errors import EndowaveError
from endowave_cl.train.config import RANGES, TrainConfig, load_config, settings_table


def test_every_key_is_listed_with_a_meaning():
    rows = settings_table()
    assert [r[0] for r in rows] == [f.name for f in fields(TrainConfig)]
    for key, default, values, meaning in rows:
        assert meaning and "\n" not in meaning and len(meaning) <= 110, key
        if key in RANGES:
            assert values, key
    by_key = {r[0]: r for r in rows}
    assert by_key["between_prob"][1:3] == ("0.5", "in [0, 1]")
    assert by_key["between_path"][2] == "linear | quadratic"
    assert by_key["use_flow"][2] == "true | false"
    assert by_key["init_time_scale"][3].startswith("longest initial temporal std")


def test_list_settings_needs_no_other_argument(capsys):
    with pytest.raises(SystemExit) as e:
        cli_main(["train", "--list-settings"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert all(f.name in out for f in fields(TrainConfig))
    assert "range / values" in out and "--recipe paper" in out


def test_a_mistyped_key_gets_the_nearest(tmp_path):
    with pytest.raises(EndowaveError, match=r"unknown key 'lamda_flow' \(did you mean 'lambda_flow'\?\)"):
        load_config(None, {"lamda_flow": "0.1"})
    toml = tmp_path / "c.toml"
    toml.write_text("itertions = 5\n")
    with pytest.raises(EndowaveError, match=r"unknown key 'itertions' \(did you mean 'iterations'\?\)"):
        load_config(str(toml))
    with pytest.raises(EndowaveError, match=r"unknown key 'zzzz'$"):
        load_config(None, {"zzzz": "1"})
