"""Every ENDOWAVE_* environment variable, parsed in one place.

Each variable has one parser here; the modules that use one call ``get(NAME)`` (or the helpers
below) and never read os.environ themselves.  A value that does not parse raises ``EnvError``
naming the variable, its value and what it accepts, a one-line error from the command line.
``check_environment()`` parses every ENDOWAVE_* variable that is set (the command line calls it
before any work, so junk fails a run in its first second, not when a kernel is first built); an
ENDOWAVE_* name that endowave-cl does not know is left alone (tools and tests have their own).

Variables (unset or empty = the default):
  ENDOWAVE_CL_DEVICE          device spec (index, platform:device or a name substring)
  ENDOWAVE_OCLGRIND           1 / true / yes / on: run on the Oclgrind simulator (the test mode)
  ENDOWAVE_CL_KERNELS         folder of the *.cl sources (default: the installed ones)
  ENDOWAVE_CL_CACHE           cache folder (compiled programs, probes, flow)
  ENDOWAVE_CL_NO_DISK_CACHE   a true flag: do not keep compiled programs on disk
  ENDOWAVE_CL_DEBUG           a true flag: tracebacks instead of one-line "unexpected" errors
  ENDOWAVE_PROJECT_VARIANT    scalar | vector
  ENDOWAVE_PROJECT_VW         2 | 4 | 8 | 16
  ENDOWAVE_RASTER_VARIANT     scalar | vector
  ENDOWAVE_RASTER_VW          4 | 8 | 16 (2 too, for tests)
  ENDOWAVE_RASTER_BW          1 | 2 | 4 | 8 | 16 (must divide the lanes)
  ENDOWAVE_NO_SELECT          a true flag: training renders every Gaussian
  ENDOWAVE_BLOCKING_STEPS     a true flag: the training loop waits for every step's outcome
                              before the next (the same results; train/trainer.py)
  ENDOWAVE_BETWEEN_TARGET     auto | device | host: where in-between targets are built (auto: the
                              device on a GPU, the host on a CPU device; train/between.py)
  ENDOWAVE_PROGRESS           bar | plain | off
  ENDOWAVE_PROGRESS_INTERVAL  seconds between plain progress lines, > 0
  ENDOWAVE_LPIPS_WEIGHTS      path of alexnet.ckpt
  ENDOWAVE_PROBE_TIMEOUT      seconds a probe child may take, > 0
  ENDOWAVE_PROBE_PLANT        test hook: "16=abort,8=hang,4=build,2=wrong"
"""
from __future__ import annotations

import math
import os
from typing import Callable, Dict, Optional

from .errors import EndowaveError


class EnvError(EndowaveError):
    """An ENDOWAVE_* environment variable holds a value that does not parse."""


TRUE = ("1", "true", "yes", "on")
FALSE = ("0", "false", "no", "off")


def _err(name: str, raw: str, want: str) -> EnvError:
    return EnvError(f"environment variable {name}={raw!r}: {want} (unset it for the default)")


def _flag(name: str, raw: str) -> bool:
    v = raw.strip().lower()
    if v in TRUE:
        return True
    if v in FALSE:
        return False
    raise _err(name, raw, f"expected one of {', '.join(TRUE + FALSE)}")


def _choice(*choices: str) -> Callable[[str, str], str]:
    def parse(name: str, raw: str) -> str:
        v = raw.strip().lower()
        if v not in choices:
            raise _err(name, raw, f"expected one of {', '.join(choices)}")
        return v
    return parse


def _int_in(*allowed: int) -> Callable[[str, str], int]:
    def parse(name: str, raw: str) -> int:
        try:
            v = int(raw.strip())
        except ValueError:
            v = None
        if v not in allowed:
            raise _err(name, raw, f"expected one of {', '.join(map(str, allowed))}")
        return v
    return parse


def _positive_float(hi: float) -> Callable[[str, str], float]:
    def parse(name: str, raw: str) -> float:
        try:
            v = float(raw.strip())
        except ValueError:
            v = math.nan
        if not (math.isfinite(v) and 0 < v <= hi):
            raise _err(name, raw, f"expected a number of seconds > 0 and <= {hi:g}")
        return v
    return parse


def _text(name: str, raw: str) -> str:
    v = raw.strip()
    if "\0" in v:
        raise _err(name, raw, "holds a NUL character")
    return v


def _plant(name: str, raw: str) -> Dict[int, str]:
    out = {}
    for item in raw.split(","):
        if not item.strip():
            continue
        w, sep, what = item.partition("=")
        try:
            lanes = int(w.strip())
        except ValueError:
            lanes = None
        if not sep or lanes is None or what.strip() not in ("abort", "hang", "build", "wrong"):
            raise _err(name, raw, "expected LANES=abort|hang|build|wrong items separated by commas")
        out[lanes] = what.strip()
    return out


PARSERS: Dict[str, Callable[[str, str], object]] = {
    "ENDOWAVE_CL_DEVICE": _text,
    "ENDOWAVE_OCLGRIND": _flag,
    "ENDOWAVE_CL_KERNELS": _text,
    "ENDOWAVE_CL_CACHE": _text,
    "ENDOWAVE_CL_NO_DISK_CACHE": _flag,
    "ENDOWAVE_CL_DEBUG": _flag,
    "ENDOWAVE_PROJECT_VARIANT": _choice("scalar", "vector"),
    "ENDOWAVE_PROJECT_VW": _int_in(2, 4, 8, 16),
    "ENDOWAVE_RASTER_VARIANT": _choice("scalar", "vector"),
    "ENDOWAVE_RASTER_VW": _int_in(2, 4, 8, 16),
    "ENDOWAVE_RASTER_BW": _int_in(1, 2, 4, 8, 16),
    "ENDOWAVE_NO_SELECT": _flag,
    "ENDOWAVE_BLOCKING_STEPS": _flag,
    "ENDOWAVE_BETWEEN_TARGET": _choice("auto", "device", "host"),
    "ENDOWAVE_PROGRESS": _choice("bar", "plain", "off"),
    "ENDOWAVE_PROGRESS_INTERVAL": _positive_float(86400.0),
    "ENDOWAVE_LPIPS_WEIGHTS": _text,
    "ENDOWAVE_PROBE_TIMEOUT": _positive_float(86400.0),
    "ENDOWAVE_PROBE_PLANT": _plant,
}


def raw(name: str) -> Optional[str]:
    """The variable's text, None when unset or blank."""
    if name not in PARSERS:
        raise KeyError(f"{name} is not an endowave-cl environment variable (add it to env.PARSERS)")
    v = os.environ.get(name)
    return v if v is not None and v.strip() else None


def get(name: str, default=None):
    """The parsed value of ``name``, ``default`` when unset or blank; EnvError when it does not parse."""
    v = raw(name)
    return default if v is None else PARSERS[name](name, v)


def flag(name: str) -> bool:
    return bool(get(name, False))


def check_environment() -> None:
    """Parse every known ENDOWAVE_* variable that is set; the first bad one raises EnvError."""
    for name in PARSERS:
        get(name)
