"""Shared fixtures and the Oclgrind test mode.

Oclgrind mode: ``ENDOWAVE_OCLGRIND=1 pytest -m oclgrind`` (or ``pytest --oclgrind``)
runs the kernel tests on the Oclgrind simulator with data-race detection on, and
fails any test after which the Oclgrind log holds a report (out-of-bounds access,
data race, uninitialised value, ...).  Tests size themselves with ``small(...)``.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
TINY_SIZE = dict(width=64, height=48, frames=10)   # the training tests' synthetic scene
TOOLS = Path(__file__).resolve().parents[1] / "tools"
BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def load_tool(name: str, folder: Path = TOOLS):
    """The module <folder>/<name>.py (tools/ by default; the scripts are not a package)."""
    import importlib.util
    spec = importlib.util.spec_from_file_location(name, Path(folder) / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
ENDONERF_PULLING = SHARED / "data" / "endonerf" / "pulling_soft_tissues"


def pytest_addoption(parser):
    parser.addoption("--oclgrind", action="store_true",
                     help="run kernel tests on the Oclgrind simulator and fail on any report")


def _oclgrind_requested(config) -> bool:
    return bool(config.getoption("--oclgrind")) or os.environ.get("ENDOWAVE_OCLGRIND", "") in ("1", "true", "yes")


_LOG = None


def pytest_configure(config):
    global _LOG
    if _oclgrind_requested(config):
        # Oclgrind reads these when its context is created, so set them before any test runs.
        os.environ["ENDOWAVE_OCLGRIND"] = "1"
        os.environ["OCLGRIND_DATA_RACES"] = "1"
        fd, _LOG = tempfile.mkstemp(prefix="oclgrind-", suffix=".log")
        os.close(fd)
        os.environ["OCLGRIND_LOG"] = _LOG


def oclgrind_active() -> bool:
    return os.environ.get("ENDOWAVE_OCLGRIND", "") in ("1", "true", "yes")


def small(normal, under_oclgrind):
    """A test size: the second under Oclgrind, which is ~1000x slower."""
    return under_oclgrind if oclgrind_active() else normal


@pytest.fixture(autouse=True)
def _oclgrind_report_check(request):
    """In Oclgrind mode, fail a test after which the Oclgrind log grew."""
    if _LOG is None:
        yield
        return
    start = os.path.getsize(_LOG)
    yield
    with open(_LOG, "r", errors="replace") as f:
        f.seek(start)
        report = f.read()
    if report.strip() and request.node.get_closest_marker("expect_oclgrind_report") is None:
        pytest.fail("Oclgrind reported:\n" + report[:8000], pytrace=False)


@pytest.fixture(scope="session")
def rt():
    """The Runtime every kernel test uses (Oclgrind in Oclgrind mode, else the default device)."""
    from endowave_cl.runtime import get_runtime
    return get_runtime()


@pytest.fixture(scope="session")
def pulling_scene():
    if not (ENDONERF_PULLING / "poses_bounds.npy").is_file():
        pytest.skip(f"shared EndoNeRF frames not present at {ENDONERF_PULLING}")
    return ENDONERF_PULLING


def make_tiny_scene(tmp_path_factory, name: str, seed: int) -> Path:
    """A TINY_SIZE synthetic scene folder (seeded) under a fresh temporary folder."""
    from endowave_cl.data.synth import make_synthetic_scene
    out = tmp_path_factory.mktemp("scene") / name
    make_synthetic_scene(out, seed=seed, **TINY_SIZE)
    return out


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
    """The 64x48, 10-frame synthetic scene (seed 3) the training, run-folder and CLI tests share:
    read it, never write into it."""
    return make_tiny_scene(tmp_path_factory, "tiny", seed=3)


def tiny_config(**kw):
    """A TrainConfig for short trainings on tiny_scene: no evaluation, checkpoint or opacity reset
    on the way unless kw asks for them."""
    from endowave_cl.train.config import TrainConfig
    return TrainConfig(**{**dict(eval_every=0, checkpoint_every=0, opacity_reset_every=100000, seed=0), **kw})
