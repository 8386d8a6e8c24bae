"""The ``endowave-cl`` command line.

Each sub-command lives in ``endowave_cl/commands/<name>.py`` and provides
``add_arguments(parser)`` and ``run(args) -> int``.  Only commands whose module is
present are offered, so ``--help`` lists exactly what works.  Only the module of the command
being run is imported (``build_parser``): ``endowave-cl --help`` imports none, and a command
imports what it needs at the top of its module.
"""
from __future__ import annotations

import argparse
import importlib
import importlib.util
import signal
import sys
import threading
import warnings
from typing import List, Optional

from . import __version__, env
from .errors import EndowaveError

# name -> one-line help; the module is endowave_cl.commands.<name>
COMMANDS = {
    "devices": "list OpenCL platforms and devices; mark the one that would be used",
    "ingest": "turn a video file or a folder of frames (mono or stereo) into a scene (EndoNeRF layout)",
    "synth": "generate a synthetic endoscopic scene (EndoNeRF layout) with ground truth",
    "flow": "precompute pseudo ground-truth optical flow for a scene",
    "train": "train an EndoWave model on a scene",
    "render": "render a trained run's test frames, a video and depth images",
    "eval": "evaluate a trained run (PSNR, SSIM, LPIPS, FPS) beside interpolation baselines",
    "export": "export a trained model at time t as a 3DGS PLY",
    "batch": "run a manifest of scenes (flow/train/eval/render/export) locally or on a Ray cluster",
    "view": "look at a trained run in a web browser: scrub time, orbit (needs the [viewer] extra)",
}

DEVICE_COMMANDS = {"devices", "train", "render", "eval", "view"}  # the ones that run OpenCL kernels


def _available():
    for name, help_ in COMMANDS.items():
        if importlib.util.find_spec(f"endowave_cl.commands.{name}") is not None:
            yield name, help_


class _NoExit(argparse.ArgumentParser):
    def error(self, message):
        raise argparse.ArgumentError(None, message)


def command_in(argv: List[str]) -> Optional[str]:
    """The sub-command that ``argv`` names (None when none), read past the top-level options the
    way the full parser reads them (``--device X`` and its abbreviations)."""
    pre = _NoExit(add_help=False)
    pre.add_argument("--device")
    pre.add_argument("command", nargs="?")
    try:
        return pre.parse_known_args(argv)[0].command
    except argparse.ArgumentError:
        return None


def build_parser(argv: Optional[List[str]] = None):
    """The parser of ``argv`` (default: sys.argv[1:]).  Every command is listed, but only the one
    that argv names has its module imported and its arguments added: the others' modules import
    what they run on (OpenCL, the trainer, ...), which ``--help`` and another command do not need."""
    chosen = command_in(sys.argv[1:] if argv is None else list(argv))
    device_help = ("OpenCL device: index or platform:device from 'endowave-cl devices', or a name "
                   "substring (default: $ENDOWAVE_CL_DEVICE, else a GPU, else the PoCL CPU device)")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--device", default=argparse.SUPPRESS, help=device_help)

    parser = argparse.ArgumentParser(
        prog="endowave-cl",
        description="EndoWave 4D Gaussian splatting for endoscopic video, on any OpenCL device.")
    parser.add_argument("--version", action="version", version=f"endowave-cl {__version__}")
    parser.add_argument("--device", default=None, help=device_help)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, help_ in _available():
        parents = [common] if name in DEVICE_COMMANDS else []
        if name != chosen:
            sub.add_parser(name, help=help_, parents=parents)
            continue
        mod = importlib.import_module(f"endowave_cl.commands.{name}")
        p = sub.add_parser(name, help=help_, description=(mod.__doc__ or help_).strip(), parents=parents,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        mod.add_arguments(p)
        p.set_defaults(_module=mod)
    return parser


class Terminated(KeyboardInterrupt):
    """SIGTERM outside a training loop (the loop itself saves and stops, train/run_folder.py)."""


def _on_sigterm(signum, frame):
    raise Terminated()


def _oserror_text(e: OSError) -> str:
    where = f"{e.filename}: " if getattr(e, "filename", None) else ""
    return f"{where}{e.strerror or e}"


def _close_progress_bars() -> None:
    """End an unfinished tqdm bar so the error message starts on its own line."""
    tqdm = sys.modules.get("tqdm")
    if tqdm is None:
        return
    for bar in list(getattr(tqdm.tqdm, "_instances", ())):
        try:
            bar.close()
        except Exception:  # noqa: BLE001  best effort: never mask the error being reported
            pass


def _debug() -> bool:
    try:
        return env.flag("ENDOWAVE_CL_DEBUG")
    except env.EnvError:
        return True


def _interrupted(name: str, e: KeyboardInterrupt) -> int:
    """The one line for SIGINT / SIGTERM; 130 or 143.  Imports nothing (a second Ctrl-C may come)."""
    rf = sys.modules.get("endowave_cl.train.run_folder")
    stop = rf is not None and isinstance(e, rf.StopRequested)
    sigterm = isinstance(e, Terminated) or (stop and "SIGTERM" in str(e))
    what = str(e) if stop else ("terminated" if sigterm else "interrupted")
    print(f"{name}: {what}", file=sys.stderr)
    return 143 if sigterm else 130


def main(argv=None) -> int:
    # signal handling first: a Ctrl-C or SIGTERM during the imports and the argument parsing below
    # (the first ~0.3 s of every command) is one line and exit 130 / 143, never a traceback.  While
    # they run, a signal is only noted (an exception raised inside an import can surface as another
    # error, or be printed and ignored by the import machinery) and acted on right after them.
    name = "endowave-cl"
    old = {}
    pending = []
    try:
        try:
            if threading.current_thread() is threading.main_thread():
                for s in (signal.SIGINT, signal.SIGTERM):
                    old[s] = signal.signal(s, lambda signum, frame: pending.append(signum))
            # PoCL's compiler prints ABI notes for the CPU rasterizer's 16-wide vectors: not for users
            warnings.filterwarnings("ignore", message="Non-empty compiler output")
            try:
                parser = build_parser(argv)
            except ImportError as e:    # a dependency of the command is missing: a broken install
                print(f"{name}: error: {e} (reinstall endowave-cl)", file=sys.stderr)
                return 1
            args = parser.parse_args(argv) if not pending else None
            if old:     # from here a signal interrupts at once (train turns it into save-and-stop)
                signal.signal(signal.SIGINT, old[signal.SIGINT])
                signal.signal(signal.SIGTERM, _on_sigterm)   # a message and exit 143, not a silent kill
            if pending:
                raise Terminated() if signal.SIGTERM in pending else KeyboardInterrupt()
            if not getattr(args, "command", None):
                parser.print_help()
                return 2
            name = f"endowave-cl {args.command}"
            return _run(args, name)
        except KeyboardInterrupt as e:
            _close_progress_bars()
            return _interrupted(name, e)
    except KeyboardInterrupt as e:    # a second one while the first was reported
        return _interrupted(name, e)
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def _run(args, name: str) -> int:
    try:
        env.check_environment()      # every ENDOWAVE_* variable parses, before any work
    except env.EnvError as e:
        print(f"{name}: error: {e}", file=sys.stderr)
        return 1
    # host_memory (ctypes.util: subprocess, tempfile) and runtime (numpy) imported here, not at the
    # top: cli.py imports nothing slow before main() has installed its signal handlers (a Ctrl-C
    # at start-up is one line, tests/cli/test_hostile.py) and --help needs neither
    from .host_memory import keep_freed_memory
    from .runtime import KernelBuildError, OpenCLUnavailable
    keep_freed_memory()          # large host temporaries reuse heap memory (host_memory.py)
    try:
        try:
            return int(args._module.run(args) or 0)
        except BaseException:
            _close_progress_bars()
            raise
    except (EndowaveError, OpenCLUnavailable, KernelBuildError) as e:
        print(f"{name}: error: {e}", file=sys.stderr)
        return 1
    except OSError as e:   # a file or folder the command could not read or write
        print(f"{name}: error: {_oserror_text(e)}", file=sys.stderr)
        return 1
    except MemoryError:
        print(f"{name}: error: out of memory", file=sys.stderr)
        return 1
    except Exception as e:  # noqa: BLE001  a bug or an unforeseen input: one line, no traceback
        if _debug():
            raise
        print(f"{name}: error: unexpected {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''} "
              f"(set ENDOWAVE_CL_DEBUG=1 for the traceback; please report it)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
