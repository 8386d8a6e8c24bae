"""Test PSNR against training steps for several runs, beside the baselines, as one PNG.

    python research/plot_test_curves.py --out research/figures/quality_late.png \
        "defaults=runs/q.log" "between fade=runs/b.log" [--baseline "DIS=34.93" ...]

Each LABEL=LOG is the output of research/quality_run.py (or of `endowave-cl train`) for one seed: its
lines "step N: test PSNR X dB" (the trainer's periodic evaluation) and, where present, the final
"seed S: test PSNR X" line, plotted at the run's last step.  --baseline adds a horizontal line.
"""
from __future__ import annotations

import argparse
import re
import sys

STEP_LINE = re.compile(r"^step (\d+): test PSNR ([0-9.]+) dB")
FINAL_LINE = re.compile(r"^seed \d+: test PSNR ([0-9.]+).* (\d+) steps")


def read_curve(path: str):
    """[(step, test PSNR)] from one log, in step order."""
    pts = {}
    with open(path, encoding="utf-8", errors="replace") as f:
        for line in f:
            m = STEP_LINE.match(line)
            if m:
                pts[int(m.group(1))] = float(m.group(2))
                continue
            m = FINAL_LINE.match(line)
            if m:
                pts[int(m.group(2))] = float(m.group(1))
    return sorted(pts.items())


def _pair(text: str, what: str):
    if "=" not in text:
        raise SystemExit(f"error: {what} expects LABEL=VALUE, got {text!r}")
    label, value = text.split("=", 1)
    return label.strip(), value.strip()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", metavar="LABEL=LOG")
    ap.add_argument("--baseline", action="append", default=[], metavar="LABEL=PSNR")
    ap.add_argument("--from-step", type=int, default=0, help="plot from this step on")
    ap.add_argument("--title", default="")
    ap.add_argument("--out", required=True, help="PNG file to write")
    a = ap.parse_args(argv)
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib.figure import Figure
    fig = Figure(figsize=(7.0, 3.8), dpi=110)
    ax = fig.add_subplot(1, 1, 1)
    for item in a.runs:
        label, path = _pair(item, "a run")
        try:
            pts = [(s, v) for s, v in read_curve(path) if s >= a.from_step]
        except OSError as e:
            print(f"error: {path}: {e.strerror}", file=sys.stderr)
            return 2
        if not pts:
            print(f"error: {path}: no 'step N: test PSNR' lines at or after step {a.from_step}", file=sys.stderr)
            return 2
        ax.plot([s for s, _ in pts], [v for _, v in pts], "o-", markersize=3, label=f"{label} (last {pts[-1][1]:.2f} dB)")
        print(f"{label}: " + ", ".join(f"{s}: {v:.2f}" for s, v in pts))
    for item in a.baseline:
        label, value = _pair(item, "--baseline")
        ax.axhline(float(value), linestyle="--", linewidth=1, color="gray")
        ax.text(ax.get_xlim()[0], float(value), f" {label} {float(value):.2f}", fontsize=7, va="bottom", color="gray")
    ax.set_xlabel("training step")
    ax.set_ylabel("test PSNR (dB)")
    if a.title:
        ax.set_title(a.title, fontsize=9)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(a.out, format="png")
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
