"""Packaging: every sub-package is installed, and the kernels travel with a non-editable install."""
from __future__ import annotations

import configparser
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _listed_packages():
    cfg = configparser.ConfigParser()
    cfg.read(ROOT / "setup.cfg")
    return {p.strip() for p in cfg["options"]["packages"].split("\n") if p.strip()}


def test_every_subpackage_is_listed_in_setup_cfg():
    found = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "endowave_cl").rglob("__init__.py")}
    missing = found - _listed_packages()
    assert not missing, f"add these to [options] packages in setup.cfg: {sorted(missing)}"


def test_kernels_are_package_data():
    assert "endowave_cl.cl" in _listed_packages()
    cfg = configparser.ConfigParser()
    cfg.read(ROOT / "setup.cfg")
    assert "*.cl" in cfg["options.package_data"]["endowave_cl.cl"]
    assert "*.h" in cfg["options.package_data"]["endowave_cl.cl"]
