"""The batch manifest (TOML): which scenes, which stages, which settings, where, with what resources.

    root = "runs/dataset"                      # output root: one run folder per scene, ROOT/<name>
    stages = ["flow", "train", "eval"]         # any of flow, train, eval, render, export
    scenes = ["data/endonerf/*", "data/own/clip3"]   # folders or globs; relative to this file

    [resources]          # per task
    cpus = 1             # CPU cores (Ray schedules by it; PoCL and torch get as many threads)
    gpus = 0             # GPUs (Ray: may be fractional; the pool: whole GPUs)
    retries = 2          # further attempts when a task's worker process dies
    device = "0:0"       # --device of every task (default: each worker's default device)

    [settings]           # TrainConfig keys (endowave_cl/train/config.py) for every scene
    iterations = 3000

    [overrides."pulling*"]   # per scene: its name (the folder name) or a glob on names
    iterations = 5000

    [eval]     fps_runs = 10, baselines = true
    [render]   all = false, video = true, fps = 15.0
    [export]   time = 0.0

Every error is one line naming the manifest file and the key (``EndowaveError``).
"""
from __future__ import annotations

import fnmatch
import glob
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

from ..commands.render import FPS_RANGE      # what render accepts: checked here, before any stage runs
from ..errors import EndowaveError
from ..train.config import TrainConfig, read_toml

STAGES = ("flow", "train", "eval", "render", "export")   # also the order a scene goes through them
DEFAULT_STAGES = ("flow", "train", "eval")
TOP_KEYS = ("root", "stages", "scenes", "resources", "settings", "overrides", "eval", "render", "export")

# [table] -> {key: (type(s), default)}; bool is checked before int (bool is an int in Python)
_OPTION_TABLES: Dict[str, Dict[str, Tuple[tuple, Any]]] = {
    "resources": {"cpus": ((int, float), 1), "gpus": ((int, float), 0), "retries": ((int,), 2),
                  "device": ((str,), None)},
    "eval": {"fps_runs": ((int,), 10), "baselines": ((bool,), True)},
    "render": {"all": ((bool,), False), "video": ((bool,), True), "fps": ((int, float), 15.0)},
    "export": {"time": ((int, float), 0.0)},
}


@dataclass
class Scene:
    name: str                     # the run folder's name under root (the scene folder's name)
    path: Path                    # absolute scene folder (may not exist: that task then fails alone)
    settings: Dict[str, Any]      # TrainConfig keys for this scene: [settings] then its overrides


@dataclass
class Manifest:
    path: Path
    root: Path
    stages: Tuple[str, ...]
    scenes: List[Scene]
    resources: Dict[str, Any]
    eval: Dict[str, Any]
    render: Dict[str, Any]
    export: Dict[str, Any]
    settings: Dict[str, Any] = field(default_factory=dict)


def _type_name(types: tuple) -> str:
    if set(types) == {int, float}:
        return "number"
    return " or ".join({int: "integer", float: "number", str: "string", bool: "true/false"}[t] for t in types)


def _check_type(src: str, key: str, value, types: tuple):
    if isinstance(value, bool) and bool not in types:
        ok = False
    else:
        ok = isinstance(value, types)
    if not ok:
        raise EndowaveError(f"{src}: key '{key}' expects {_type_name(types)}, got {type(value).__name__} {value!r}")
    return value


def _options(src: str, table: str, data: dict) -> Dict[str, Any]:
    spec = _OPTION_TABLES[table]
    raw = data.get(table, {})
    if not isinstance(raw, dict):
        raise EndowaveError(f"{src}: '{table}' must be a table ([{table}]), got {type(raw).__name__}")
    out = {k: d for k, (_, d) in spec.items()}
    for k, v in raw.items():
        if k not in spec:
            raise EndowaveError(f"{src}: unknown key '{table}.{k}' (expected one of {', '.join(spec)})")
        out[k] = _check_type(src, f"{table}.{k}", v, spec[k][0])
    return out


MAX_TASK_CPUS = 1024     # resources.cpus: threads per task (1e300 went into POCL_MAX_PTHREAD_COUNT and crashed)
MIN_TASK_CPUS = 0.01     # ... and tasks per core (1e-300 made a pool of 1e300 workers: OverflowError)


def _check_ranges(src: str, m: Manifest) -> None:
    r = m.resources
    if not (math.isfinite(r["cpus"]) and r["cpus"] > 0):
        raise EndowaveError(f"{src}: key 'resources.cpus' must be > 0, got {r['cpus']:g}")
    if not MIN_TASK_CPUS <= r["cpus"] <= MAX_TASK_CPUS:
        raise EndowaveError(f"{src}: key 'resources.cpus' must be from {MIN_TASK_CPUS:g} to {MAX_TASK_CPUS} (CPU "
                            f"cores per task: PoCL and torch start as many threads, the pool as many workers "
                            f"as fit), got {r['cpus']:g}")
    if not (math.isfinite(r["gpus"]) and r["gpus"] >= 0):
        raise EndowaveError(f"{src}: key 'resources.gpus' must be >= 0, got {r['gpus']}")
    if r["retries"] < 0:
        raise EndowaveError(f"{src}: key 'resources.retries' must be >= 0, got {r['retries']}")
    if m.eval["fps_runs"] < 0:
        raise EndowaveError(f"{src}: key 'eval.fps_runs' must be >= 0, got {m.eval['fps_runs']}")
    if not (math.isfinite(m.render["fps"]) and FPS_RANGE[0] <= m.render["fps"] <= FPS_RANGE[1]):
        raise EndowaveError(f"{src}: key 'render.fps' must be from {FPS_RANGE[0]:g} to {FPS_RANGE[1]:g}, "
                            f"got {m.render['fps']:g}")
    if not 0.0 <= m.export["time"] <= 1.0:
        raise EndowaveError(f"{src}: key 'export.time' must be in [0, 1], got {m.export['time']}")


def _stages(src: str, data: dict) -> Tuple[str, ...]:
    raw = data.get("stages", list(DEFAULT_STAGES))
    if not isinstance(raw, list) or not raw or not all(isinstance(s, str) for s in raw):
        raise EndowaveError(f"{src}: key 'stages' must be a non-empty list of stage names "
                            f"({', '.join(STAGES)}), got {raw!r}")
    for s in raw:
        if s not in STAGES:
            raise EndowaveError(f"{src}: key 'stages': unknown stage {s!r} (expected any of {', '.join(STAGES)})")
    return tuple(s for s in STAGES if s in raw)   # the order a scene goes through them


def _scenes(src: str, base: Path, data: dict) -> List[Tuple[str, Path]]:
    """(name, absolute folder) per scene, in manifest order, each folder once."""
    raw = data.get("scenes")
    if raw is None:
        raise EndowaveError(f"{src}: key 'scenes' is missing (a list of scene folders or globs)")
    if isinstance(raw, str):
        raw = [raw]
    if not isinstance(raw, list) or not raw or not all(isinstance(s, str) and s.strip() for s in raw):
        raise EndowaveError(f"{src}: key 'scenes' must be a non-empty list of folder paths or globs, got {raw!r}")
    found: List[Path] = []
    for entry in raw:
        pattern = os.path.expanduser(entry)
        pattern = pattern if os.path.isabs(pattern) else str(base / pattern)
        if glob.has_magic(pattern):
            hits = sorted(Path(p) for p in glob.glob(pattern) if Path(p).is_dir())
            if not hits:
                raise EndowaveError(f"{src}: key 'scenes': {entry!r} matches no folder")
        else:
            # a folder that is missing is not a manifest error: its tasks fail alone with the
            # scene loader's message, and the other scenes go on
            hits = [Path(pattern)]
        for h in hits:
            h = Path(os.path.abspath(h))
            if h not in found:
                found.append(h)
    by_name: Dict[str, Path] = {}
    for p in found:
        if p.name in by_name:
            raise EndowaveError(f"{src}: key 'scenes': two scenes are named {p.name!r} ({by_name[p.name]} and {p}); "
                                f"each scene's run folder is ROOT/<folder name>, so the names must differ")
        by_name[p.name] = p
    return list(by_name.items())


def _settings(src: str, where: str, raw) -> Dict[str, Any]:
    """A table of TrainConfig keys, checked (unknown keys, types, ranges) by TrainConfig itself."""
    if not isinstance(raw, dict):
        raise EndowaveError(f"{src}: '{where}' must be a table of training settings, got {type(raw).__name__}")
    TrainConfig.from_dict(raw, source=f"{src} [{where}]")
    return dict(raw)


def load_manifest(path) -> Manifest:
    path = Path(path)
    src = str(path)
    data = read_toml(path, "manifest file")
    for k in data:
        if k not in TOP_KEYS:
            raise EndowaveError(f"{src}: unknown key '{k}' (expected any of {', '.join(TOP_KEYS)})")
    base = path.resolve().parent
    root = data.get("root")
    if not isinstance(root, str) or not root.strip():
        raise EndowaveError(f"{src}: key 'root' must name the output folder, got {root!r}")
    root_path = Path(os.path.expanduser(root))
    root_path = Path(os.path.abspath(root_path if root_path.is_absolute() else base / root_path))
    if root_path.exists() and not root_path.is_dir():
        raise EndowaveError(f"{src}: key 'root': {root_path} exists and is not a folder")
    stages = _stages(src, data)
    shared = _settings(src, "settings", data.get("settings", {}))
    scenes = _scenes(src, base, data)
    overrides = data.get("overrides", {})
    if not isinstance(overrides, dict) or not all(isinstance(v, dict) for v in overrides.values()):
        raise EndowaveError(f"{src}: 'overrides' must hold one table per scene name or glob, "
                            f"e.g. [overrides.\"pulling*\"]")
    per_scene: Dict[str, Dict[str, Any]] = {name: dict(shared) for name, _ in scenes}
    for pattern, table in overrides.items():
        where = f"overrides.{pattern}"
        _settings(src, where, table)
        hit = [name for name, _ in scenes if fnmatch.fnmatchcase(name, pattern)]
        if not hit:
            raise EndowaveError(f"{src}: key '{where}' matches no scene (scene names: "
                                f"{', '.join(n for n, _ in scenes)})")
        for name in hit:
            per_scene[name].update(table)
    out = []
    for name, p in scenes:
        _settings(src, f"overrides for {name}", per_scene[name])   # the merged values, checked together
        out.append(Scene(name, p, per_scene[name]))
    m = Manifest(path=path, root=root_path, stages=stages, scenes=out,
                 resources=_options(src, "resources", data), eval=_options(src, "eval", data),
                 render=_options(src, "render", data), export=_options(src, "export", data), settings=shared)
    _check_ranges(src, m)
    return m


def setting(scene: Scene, key: str):
    """The effective value of a TrainConfig key for this scene (its setting, else the default)."""
    return scene.settings.get(key, getattr(TrainConfig(), key))


def remote_address(cli_address: Optional[str]) -> Optional[str]:
    """The Ray cluster to use: --address, else $RAY_ADDRESS, else None (local)."""
    return cli_address or os.environ.get("RAY_ADDRESS") or None
