"""Checkpoint files (the model layer's I/O, torch-free): one .npz per save, written atomically,
validated on load; and finding a run folder's checkpoints.  Training (train/run_folder.py),
export, evaluation and the viewer read them from here.

Layout of the .npz (no pickled objects; np.load runs with allow_pickle=False):
    format                      int, CHECKPOINT_FORMAT
    step                        int
    param/<name>                the seven parameter arrays (gaussians.py layout)
    adam/step                   int (absent with the adam/ entries when no Adam state was saved)
    adam/exp_avg/<name>, adam/exp_avg_sq/<name>   moments, same shapes as the parameters
    config_json                 the TrainConfig as JSON text
    extra_json                  JSON-serialisable entries of ``extra``
    extra/<key>                 numpy-array entries of ``extra``
Files are named checkpoint_<step:07d>.npz in the run folder (``checkpoint_path``).
"""
from __future__ import annotations

import contextlib
import json
import os
import re
import zipfile
from pathlib import Path
from typing import Any, Callable, Dict, List, Mapping, Optional

import numpy as np

from .atomic import atomic_open
from .errors import EndowaveError
from .gaussians import PARAM_NAMES, Gaussians

# 2: the Gaussians are rendered with gaussians.LOWPASS = 0.1.  Format 1 (the 3DGS low-pass, 0.3) is
# refused: its Gaussians were fitted to another footprint and would render differently here.
CHECKPOINT_FORMAT = 2
FORMAT_NOTES = {1: "format 1 was trained with the 3DGS low-pass of 0.3 px^2, which this version no longer "
                   "renders; train it again with this version"}
CHECKPOINT_RE = re.compile(r"^checkpoint_(\d+)\.npz$")


def checkpoint_path(run_dir, step: int) -> Path:
    return Path(run_dir) / f"checkpoint_{int(step):07d}.npz"


def latest_checkpoint(run_dir) -> Optional[Path]:
    """The checkpoint_<step>.npz with the highest step in run_dir (None when there is none)."""
    d = Path(run_dir)
    if not d.is_dir():
        return None
    best = None
    for p in d.iterdir():
        m = CHECKPOINT_RE.match(p.name)
        if m and p.is_file() and (best is None or int(m.group(1)) > best[0]):
            best = (int(m.group(1)), p)
    return None if best is None else best[1]


def _json_text(obj: Any, what: str, path) -> np.ndarray:
    try:
        return np.array(json.dumps(obj))
    except (TypeError, ValueError) as e:
        raise EndowaveError(f"{path}: cannot save {what}: {e}") from None


def save_checkpoint(path, gaussians: Gaussians, adam_state: Optional[Mapping[str, Any]], step: int,
                    config_dict: Mapping[str, Any], extra: Optional[Mapping[str, Any]] = None) -> Path:
    """Write the checkpoint atomically (temporary file in the same folder, then os.replace)."""
    path = Path(path)
    arrays: Dict[str, np.ndarray] = {"format": np.array(CHECKPOINT_FORMAT), "step": np.array(int(step))}
    for n in PARAM_NAMES:
        arrays[f"param/{n}"] = np.ascontiguousarray(getattr(gaussians, n), np.float32)
    if adam_state is not None:
        arrays["adam/step"] = np.array(int(adam_state["step"]))
        for key in ("exp_avg", "exp_avg_sq"):
            for n in PARAM_NAMES:
                arrays[f"adam/{key}/{n}"] = np.ascontiguousarray(adam_state[key][n], np.float32)
    arrays["config_json"] = _json_text(dict(config_dict), "the config", path)
    extra = dict(extra or {})
    plain = {k: v for k, v in extra.items() if not isinstance(v, np.ndarray)}
    for k, v in extra.items():
        if isinstance(v, np.ndarray):
            if v.dtype == object:
                raise EndowaveError(f"{path}: cannot save extra[{k!r}]: object arrays are not allowed")
            arrays[f"extra/{k}"] = v
    arrays["extra_json"] = _json_text(plain, "extra", path)

    with atomic_open(path) as f:
        np.savez(f, **arrays)
    return path


def _check_shapes(path, params: Dict[str, np.ndarray]) -> None:
    means = params["means"]
    if means.ndim != 2 or means.shape[1] != 4:
        raise EndowaveError(f"{path}: param/means has shape {means.shape}, expected [N, 4]")
    N = means.shape[0]
    sh = params["sh"]
    if sh.ndim != 4 or sh.shape[0] != N or sh.shape[3] != 3 or round(np.sqrt(sh.shape[2])) ** 2 != sh.shape[2]:
        raise EndowaveError(f"{path}: param/sh has shape {sh.shape}, expected [{N}, NT+1, K, 3] with K a square")
    want = {"scales": (N, 4), "quat_l": (N, 4), "quat_r": (N, 4), "opacity": (N,), "phase": (N, sh.shape[1])}
    for n, shape in want.items():
        if params[n].shape != shape:
            raise EndowaveError(f"{path}: param/{n} has shape {params[n].shape}, expected {list(shape)}")
    for n, a in params.items():
        if a.dtype != np.float32:
            raise EndowaveError(f"{path}: param/{n} has dtype {a.dtype}, expected float32")


def load_checkpoint(path) -> Dict[str, Any]:
    """{"gaussians": Gaussians, "adam_state": dict | None, "step": int, "config": dict, "extra": dict}.

    Raises EndowaveError naming the file for a missing, truncated, corrupt or inconsistent file.
    """
    path = Path(path)
    if not path.is_file():
        raise EndowaveError(f"{path}: checkpoint file does not exist")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}  # reads (and CRC-checks) every member now
    except (zipfile.BadZipFile, zipfile.LargeZipFile, ValueError, OSError, EOFError, KeyError) as e:
        raise EndowaveError(f"{path}: not a readable checkpoint (truncated or corrupt file?): {e}") from None

    def need(key):
        if key not in data:
            raise EndowaveError(f"{path}: checkpoint has no entry '{key}' (not an endowave-cl checkpoint?)")
        return data[key]

    fmt = int(need("format"))
    if fmt != CHECKPOINT_FORMAT:
        note = FORMAT_NOTES.get(fmt, "")
        raise EndowaveError(f"{path}: checkpoint format {fmt}, this version reads {CHECKPOINT_FORMAT}"
                            + (f" ({note})" if note else ""))
    params = {n: need(f"param/{n}") for n in PARAM_NAMES}
    _check_shapes(path, params)
    adam_state = None
    if "adam/step" in data:
        adam_state = {"step": int(data["adam/step"]), "exp_avg": {}, "exp_avg_sq": {}}
        for key in ("exp_avg", "exp_avg_sq"):
            for n in PARAM_NAMES:
                a = need(f"adam/{key}/{n}")
                if a.shape != params[n].shape:
                    raise EndowaveError(f"{path}: adam/{key}/{n} has shape {a.shape}, "
                                        f"parameter has {params[n].shape}")
                adam_state[key][n] = a
    try:
        config = json.loads(str(need("config_json")))
        extra = json.loads(str(need("extra_json")))
    except json.JSONDecodeError as e:
        raise EndowaveError(f"{path}: corrupt JSON entry in checkpoint: {e}") from None
    for k, v in data.items():
        if k.startswith("extra/"):
            extra[k[len("extra/"):]] = v
    return {"gaussians": Gaussians(**params), "adam_state": adam_state, "step": int(need("step")),
            "config": config, "extra": extra}


def checkpoints_by_step(run_dir) -> List[Path]:
    """checkpoint_<step>.npz files of run_dir, lowest step first."""
    d = Path(run_dir)
    if not d.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in d.iterdir()
             if (m := CHECKPOINT_RE.match(p.name)) and p.is_file()]
    return [p for _, p in sorted(found)]


def load_newest_good_checkpoint(run_dir, log: Callable[[str], None] = print, set_aside: bool = False):
    """(path, checkpoint dict) of the newest checkpoint that reads back, or (None, None) when there
    is none.  An unreadable newer one is reported (and renamed to *.corrupt with ``set_aside``, so
    retention and later resumes never count it); when none reads back, its error is raised."""
    cks = checkpoints_by_step(run_dir)
    first_error = None
    for p in reversed(cks):
        try:
            return p, load_checkpoint(p)
        except EndowaveError as e:
            first_error = first_error or e
            older = "an older one" if p != cks[0] else "no older one"
            if set_aside:
                with contextlib.suppress(OSError):
                    os.replace(p, p.with_name(p.name + ".corrupt"))
                log(f"warning: {e}; set aside as {p.name}.corrupt, trying {older}")
            else:
                log(f"warning: {e}; trying {older}")
    if first_error is not None:
        raise first_error
    return None, None
