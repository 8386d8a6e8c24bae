"""Look at a trained run in a web browser: scrub through time, orbit the tissue.

Serves a local page (viser; nothing is downloaded at run time) until Ctrl-C.  The image is rendered
by our OpenCL rasterizer at the browser's camera and the slider's time and streamed to the page; a
browser mode sends the 3D Gaussians at that time to the browser's own splat renderer instead.
The camera starts at the first frame's training camera.  Needs the [viewer] extra:
pip install -c constraints.txt ".[viewer]"."""
from __future__ import annotations

import contextlib
import io
import time
from pathlib import Path

from ..checkpoint import checkpoints_by_step
from ..cli import Terminated
from ..errors import EndowaveError
from ..run_io import load_run
from ..runtime import get_runtime
from ..viewer import ViewerModel
from ..viewer_app import ViewerApp, port_problem

DEMO_HINT = "make one with: endowave-cl train --demo --out runs/demo   (about 1.5 minutes on 2 CPU cores)"


def add_arguments(p) -> None:
    p.add_argument("run", nargs="?", help="run folder written by endowave-cl train (omit with --demo)")
    p.add_argument("--demo", action="store_true", help="open the newest run under ./runs/")
    p.add_argument("--port", type=int, default=8080, help="port to serve on (default 8080)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1: this machine only; 0.0.0.0 for every interface)")
    p.add_argument("--scene", help="scene folder (default: the one the run was trained on)")


def newest_run(root: Path):
    """The run folder under ``root`` whose newest checkpoint is the most recent, or None."""
    best, best_m = None, -1.0
    if not root.is_dir():
        return None
    for d in root.iterdir():
        if not (d / "config.json").is_file():
            continue
        cks = list(d.glob("checkpoint_*.npz"))
        if cks:
            m = max(c.stat().st_mtime for c in cks)
            if m > best_m:
                best, best_m = d, m
    return best


def run(args) -> int:
    if not 0 < args.port < 65536:
        raise EndowaveError(f"--port must be in 1..65535, got {args.port}")
    if args.demo and args.run:
        raise EndowaveError("give a run folder or --demo, not both")
    if args.demo:
        found = newest_run(Path("runs"))
        if found is None:
            raise EndowaveError(f"no trained run under {Path('runs').resolve()}; {DEMO_HINT}")
        run_dir = found
    elif args.run:
        run_dir = Path(args.run)
    else:
        raise EndowaveError(f"name a run folder, or use --demo to open the newest under runs/ ({DEMO_HINT})")
    if not run_dir.is_dir():
        raise EndowaveError(f"{run_dir}: run folder not found")
    # the run's own problems first, before what the viewer needs installed
    if not (run_dir / "config.json").is_file():
        raise EndowaveError(f"{run_dir}: not a training run (no config.json); train one with endowave-cl train")
    if not checkpoints_by_step(run_dir):
        raise EndowaveError(f"{run_dir}: no checkpoint_*.npz yet; the viewer opens a run once training has "
                            f"saved one")
    try:
        import viser  # noqa: F401
    except ImportError:
        raise EndowaveError("the viewer needs viser: in a checkout of endowave-cl, pip install -c constraints.txt "
                            "\".[viewer]\" (elsewhere: pip install \"viser>=1.1\")") from None

    # the port is checked before the (slower) model load so a taken port is reported at once
    problem = port_problem(args.host, args.port)
    if problem:
        raise EndowaveError(problem)
    r = load_run(run_dir, args.scene)
    rt = get_runtime(getattr(args, "device", None))
    model = ViewerModel(r, rt)
    title = (f"{run_dir.name}: {Path(r.scene.path).name}, {len(r.gaussians)} Gaussians, step {r.step}, "
             f"{len(r.scene.frames)} frames")
    app = ViewerApp(model, args.host, args.port, title).start()
    try:   # the address is printed inside: a Ctrl-C right after it (before the loop) is a stop too
        print(f"viewing {run_dir} ({title}) on {rt.name}")
        print(f"open {app.url} in a browser; Ctrl-C to stop", flush=True)
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt as e:
        if isinstance(e, Terminated):   # SIGTERM: the CLI reports it and exits 143
            raise
        print("stopped")                # Ctrl-C is how a user ends the viewer: not an error
        return 0
    finally:
        with contextlib.redirect_stdout(io.StringIO()):   # viser's own "Server stopped" line
            app.stop()
