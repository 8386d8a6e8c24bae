"""Export a trained run's model at time t as a standard 3DGS PLY (opens in common Gaussian viewers)."""
from __future__ import annotations


def add_arguments(p) -> None:
    p.add_argument("run", help="run folder written by endowave-cl train")
    p.add_argument("--time", type=float, default=0.0, help="normalised time in [0, 1] (frame i of N is i/(N-1))")
    p.add_argument("--out", help="PLY path (default RUN/model_t<time>.ply)")


def run(args) -> int:
    from pathlib import Path

    from ..errors import EndowaveError
    from ..export_ply import export_ply
    from ..train.checkpoint import latest_checkpoint, load_checkpoint
    if not 0.0 <= args.time <= 1.0:
        raise EndowaveError(f"--time must be in [0, 1], got {args.time}")
    ck = latest_checkpoint(Path(args.run))
    if ck is None:
        raise EndowaveError(f"{args.run}: no checkpoint_*.npz found")
    g = load_checkpoint(ck)["gaussians"]
    out = Path(args.out) if args.out else Path(args.run) / f"model_t{args.time:.3f}.ply"
    n = export_ply(out, g, args.time)
    print(f"wrote {out} ({n if n is not None else '?'} Gaussians at t = {args.time})")
    return 0
