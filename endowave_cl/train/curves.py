"""Training curves: RUN/train_curves.csv always, TensorBoard events under RUN/tensorboard/ when the
``tensorboard`` package is installed, and RUN/train_curves.png at the end of a run.

Each row is one log step (``log_every``) of ``Trainer.history``: the step, the loss terms and the
training PSNR (moving averages over the training-frame steps, as the progress bar shows them), the
Gaussian count and the median step time since the previous row.  The CSV is rewritten atomically
at every log step (a killed run leaves a complete file); the events are appended as they come.
"""
from __future__ import annotations

import io
from pathlib import Path
from typing import Dict, List, Optional

from ..atomic import write_bytes_atomic

CSV_NAME = "train_curves.csv"
PNG_NAME = "train_curves.png"
TB_DIR = "tensorboard"
FIRST = ("step", "total", "psnr", "gaussians", "step_ms")   # columns first in the CSV, in this order


def columns(history: List[Dict[str, float]]) -> List[str]:
    keys = []
    for h in history:
        for k in h:
            if k not in keys:
                keys.append(k)
    return [k for k in FIRST if k in keys] + sorted(k for k in keys if k not in FIRST)


def csv_text(history: List[Dict[str, float]]) -> str:
    cols = columns(history)
    lines = [",".join(cols)]
    for h in history:
        lines.append(",".join("" if h.get(c) is None else f"{h[c]:.6g}" if isinstance(h[c], float) else str(h[c])
                              for c in cols))
    return "\n".join(lines) + "\n"


def write_csv(run_dir, history) -> Path:
    path = Path(run_dir) / CSV_NAME
    write_bytes_atomic(path, csv_text(history).encode())
    return path


class TensorBoard:
    """Scalars to RUN/tensorboard/ through torch's SummaryWriter; does nothing without tensorboard."""

    def __init__(self, run_dir, start_step: int = 0):
        self.writer = None
        try:
            import tensorboard  # noqa: F401  torch.utils.tensorboard needs it
            from torch.utils.tensorboard import SummaryWriter
        except Exception:  # noqa: BLE001  not installed (or broken): the CSV still has everything
            return
        try:
            # purge_step: a resumed run drops the events a killed run wrote after its checkpoint
            self.writer = SummaryWriter(str(Path(run_dir) / TB_DIR), purge_step=start_step or None)
        except Exception:  # noqa: BLE001
            self.writer = None

    @property
    def active(self) -> bool:
        return self.writer is not None

    def add(self, row: Dict[str, float]) -> None:
        if self.writer is None:
            return
        step = int(row["step"])
        for k, v in row.items():
            if k != "step" and v is not None:
                group = "loss" if k not in ("psnr", "gaussians", "step_ms") else "train"
                self.writer.add_scalar(f"{group}/{k}", float(v), step)
        self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None


def write_png(run_dir, history, title: Optional[str] = None) -> Optional[Path]:
    """Four panels (loss terms, training PSNR, Gaussians, step time) against the step; None when the
    history has fewer than two rows."""
    if len(history) < 2:
        return None
    import matplotlib      # on first use: about 1 s to import; Agg chosen before pyplot loads
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    steps = [h["step"] for h in history]
    fig, axes = plt.subplots(2, 2, figsize=(11, 7), constrained_layout=True)
    ax = axes[0, 0]
    terms = [k for k in columns(history) if k not in FIRST]
    for k in ["total"] + terms:
        ys = [h.get(k) for h in history]
        if any(y is not None and y > 0 for y in ys):
            ax.plot(steps, [y if y is not None and y > 0 else float("nan") for y in ys], label=k,
                    lw=2 if k == "total" else 1)
    ax.set_yscale("log")
    ax.set_title("loss (moving average)")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    for a, key, name in ((axes[0, 1], "psnr", "training PSNR (dB)"), (axes[1, 0], "gaussians", "Gaussians"),
                         (axes[1, 1], "step_ms", "step time (ms, median)")):
        a.plot(steps, [h.get(key, float("nan")) for h in history])
        a.set_title(name)
    for a in axes.flat:
        a.set_xlabel("step")
        a.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    path = Path(run_dir) / PNG_NAME
    write_bytes_atomic(path, buf.getvalue())
    return path
