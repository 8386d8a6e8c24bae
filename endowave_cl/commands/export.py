"""Export a trained run's model at time t as a standard 3DGS PLY (opens in common Gaussian viewers),
in the units of the scene's depth files and poses."""
from __future__ import annotations


def add_arguments(p) -> None:
    p.add_argument("run", help="run folder written by endowave-cl train")
    p.add_argument("--time", type=float, default=0.0, help="normalised time in [0, 1] (frame i of N is i/(N-1))")
    p.add_argument("--out", help="PLY path (default RUN/model_t<time>.ply)")


def run(args) -> int:
    import sys
    from pathlib import Path

    from ..errors import EndowaveError
    from ..export_ply import export_ply
    from ..checkpoint import load_newest_good_checkpoint
    if not 0.0 <= args.time <= 1.0:
        raise EndowaveError(f"--time must be in [0, 1], got {args.time}")
    run = Path(args.run)
    if not run.is_dir():
        raise EndowaveError(f"{run}: run folder not found")
    out = Path(args.out) if args.out else run / f"model_t{args.time:.3f}.ply"
    if out.is_dir():
        raise EndowaveError(f"{out}: is a folder; --out names the PLY file to write")
    for parent in out.parents:
        if parent.exists():
            if not parent.is_dir():
                raise EndowaveError(f"{out}: cannot write there: {parent} is a file")
            break
    # the newest checkpoint that reads back (an older one, with a warning, if the newest is corrupt)
    ck, state = load_newest_good_checkpoint(run, log=lambda m: print(m, file=sys.stderr))
    if ck is None:
        raise EndowaveError(f"{args.run}: no checkpoint_*.npz found")
    g = state["gaussians"]
    from ..run_io import run_world_scale
    world_scale = run_world_scale(state, ck)
    n = export_ply(out, g, args.time, scale=1.0 / world_scale)   # in the scene files' units
    print(f"wrote {out} ({n if n is not None else '?'} Gaussians at t = {args.time}, in the units of "
          f"the scene's depth files and poses)")
    return 0
