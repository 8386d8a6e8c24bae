"""`endowave-cl train --list-settings` names every TrainConfig key with its default, range and a
one-line meaning; a mistyped key in --set or a TOML file gets a "did you mean" (issue 59)."""
from __future__ import annotations

import pytest

from endowave_cl.cli import main as cli_main
from endowave_cl.errors import EndowaveError
from endowave_cl.train.config import FLAT, KEYS, RANGES, SECTIONS, load_config, settings_table


def test_every_key_is_listed_with_a_meaning():
    rows = settings_table()
    assert [r[1] for r in rows] == list(KEYS) and KEYS[0] == "recipe" and len(KEYS) == len(set(KEYS))
    for section, key, default, values, meaning in rows:
        assert meaning and "\n" not in meaning and len(meaning) <= 110, key
        assert section == (FLAT[key][0] if key != "recipe" else "")
        if key in RANGES:
            assert values, key
    by_key = {r[1]: r[2:] for r in rows}
    assert by_key["between_prob"][:2] == ("0.7", "in [0, 1]")
    assert by_key["between_path"][1] == "linear | quadratic"
    assert by_key["use_flow"][1] == "true | false"
    assert by_key["init_time_scale"][2].startswith("longest initial temporal std")


def test_list_settings_needs_no_other_argument(capsys):
    with pytest.raises(SystemExit) as e:
        cli_main(["train", "--list-settings"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert all(key in out for key in KEYS)
    assert "range / values" in out and "--recipe paper" in out
    # grouped by section, in SECTIONS' order, each key under its own section's heading
    heads = [out.index(f"\n[{name}]") for name in SECTIONS]
    assert heads == sorted(heads)
    for key, (name, _) in FLAT.items():
        at = out.index(f"\n{key} ")
        assert heads[list(SECTIONS).index(name)] < at, key
        later = [h for h in heads if h > heads[list(SECTIONS).index(name)]]
        assert not later or at < later[0], key


def test_a_mistyped_key_gets_the_nearest(tmp_path):
    with pytest.raises(EndowaveError, match=r"unknown key 'lamda_flow' \(did you mean 'lambda_flow'\?\)"):
        load_config(None, {"lamda_flow": "0.1"})
    toml = tmp_path / "c.toml"
    toml.write_text("itertions = 5\n")
    with pytest.raises(EndowaveError, match=r"unknown key 'itertions' \(did you mean 'iterations'\?\)"):
        load_config(str(toml))
    with pytest.raises(EndowaveError, match=r"unknown key 'zzzz'$"):
        load_config(None, {"zzzz": "1"})
