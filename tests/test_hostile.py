"""Issue 57, the second hostile-user sweep: each test here reproduced a defect before its fix
(tools/sweep_cli.py runs the wider sweep these came from).  Tiny scenes, a few steps."""
from __future__ import annotations

import contextlib
import io
import os
import signal
import subprocess
import sys
import time

import pytest

from endowave_cl import cli


def _main(*argv):
    """(rc, stdout, stderr) of cli.main in this process."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli.main([str(a) for a in argv])
    return rc, out.getvalue(), err.getvalue()


def _one_line(rc, err, *words):
    assert rc == 1, (rc, err)
    lines = err.strip().splitlines()
    assert "Traceback" not in err and len(lines) == 1, err
    assert "unexpected" not in err, err
    for w in words:
        assert w in err, (w, err)
    return lines[0]


# ------------------------------------------------------------------ ENDOWAVE_* variables (item 14)
@pytest.mark.parametrize("name,value", [
    ("ENDOWAVE_RASTER_VW", "junk"), ("ENDOWAVE_RASTER_VW", "3"), ("ENDOWAVE_PROJECT_VW", "x"),
    ("ENDOWAVE_PROGRESS_INTERVAL", "soon"), ("ENDOWAVE_PROGRESS_INTERVAL", "-1"),
    ("ENDOWAVE_PROGRESS_INTERVAL", "nan"), ("ENDOWAVE_RASTER_VARIANT", "fast"),
    ("ENDOWAVE_PROJECT_VARIANT", "1"), ("ENDOWAVE_RASTER_BW", "3"), ("ENDOWAVE_PROGRESS", "loud"),
    ("ENDOWAVE_PROBE_TIMEOUT", "0"), ("ENDOWAVE_PROBE_PLANT", "16=explode"), ("ENDOWAVE_NO_SELECT", "maybe"),
    ("ENDOWAVE_OCLGRIND", "2"), ("ENDOWAVE_CL_NO_DISK_CACHE", "please"),
])
def test_junk_environment_variable_is_named_before_any_work(monkeypatch, tmp_path, name, value):
    monkeypatch.setenv(name, value)
    rc, out, err = _main("export", tmp_path / "norun")      # would fail later for another reason
    _one_line(rc, err, name, repr(value))


def test_every_variable_is_parsed_in_env_py():
    """No module reads an ENDOWAVE_* variable from os.environ itself."""
    import re
    from pathlib import Path
    import endowave_cl
    root = Path(endowave_cl.__file__).parent
    offenders = []
    for p in root.rglob("*.py"):
        if p.name == "env.py":
            continue
        for i, line in enumerate(p.read_text().splitlines(), 1):
            if re.search(r"environ(\.get)?\s*[\(\[]\s*(\"ENDOWAVE_|ENV_)", line) or \
                    re.search(r"getenv\(\s*(\"ENDOWAVE_|ENV_)", line):
                offenders.append(f"{p.relative_to(root)}:{i}: {line.strip()}")
    assert not offenders, offenders


def test_env_values_parse():
    from endowave_cl import env
    os.environ.pop("ENDOWAVE_RASTER_VW", None)
    assert env.get("ENDOWAVE_RASTER_VW") is None
    assert env.PARSERS["ENDOWAVE_RASTER_VW"]("ENDOWAVE_RASTER_VW", " 8 ") == 8
    assert env.PARSERS["ENDOWAVE_PROBE_PLANT"]("ENDOWAVE_PROBE_PLANT", "16=abort, 8=hang") == {16: "abort", 8: "hang"}
    assert env.PARSERS["ENDOWAVE_NO_SELECT"]("ENDOWAVE_NO_SELECT", "Yes") is True


# ------------------------------------------------------------------ Ctrl-C at start-up (item 15)
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_during_startup_is_one_line(tmp_path, sig):
    """A signal in the first fraction of a second (imports, argument parsing): one line, 130 / 143.
    (Not before ~0.06 s: that is the interpreter's own start-up, before endowave-cl runs.)"""
    code = 130 if sig == signal.SIGINT else 143
    for delay in (0.08, 0.15, 0.25, 0.35):
        p = subprocess.Popen([sys.executable, "-m", "endowave_cl", "eval", str(tmp_path / "norun")],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        time.sleep(delay)
        p.send_signal(sig)
        _, err = p.communicate(timeout=60)
        assert "Traceback" not in err, (delay, err)
        if p.returncode in (code, 1):    # 1: it had already finished with its error
            assert len(err.strip().splitlines()) <= 1, err
        else:
            assert p.returncode == -sig, (delay, p.returncode, err)
