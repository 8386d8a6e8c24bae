"""The ``endowave-cl`` command line.

Each sub-command lives in ``endowave_cl/commands/<name>.py`` and provides
``add_arguments(parser)`` and ``run(args) -> int``.  Only commands whose module is
present are offered, so ``--help`` lists exactly what works.
"""
from __future__ import annotations

import signal
import sys
import threading

from . import __version__

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
    import importlib.util
    for name, help_ in COMMANDS.items():
        if importlib.util.find_spec(f"endowave_cl.commands.{name}") is not None:
            yield name, help_


def build_parser():
    import argparse
    import importlib
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
        mod = importlib.import_module(f"endowave_cl.commands.{name}")
        p = sub.add_parser(name, help=help_, description=(mod.__doc__ or help_).strip(),
                           parents=[common] if name in DEVICE_COMMANDS else [],
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
    from . import env
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
            import warnings
            # PoCL's compiler prints ABI notes for the CPU rasterizer's 16-wide vectors: not for users
            warnings.filterwarnings("ignore", message="Non-empty compiler output")
            parser = build_parser()
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
    from . import env
    from .errors import EndowaveError
    try:
        env.check_environment()      # every ENDOWAVE_* variable parses, before any work
    except env.EnvError as e:
        print(f"{name}: error: {e}", file=sys.stderr)
        return 1
    from .host_memory import keep_freed_memory
    keep_freed_memory()          # large host temporaries reuse heap memory (host_memory.py)
    from .runtime import KernelBuildError, OpenCLUnavailable
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
