"""`endowave-cl batch` (issue 17): manifests, completion records, and whole manifests run on a local
Ray cluster started here (2 CPUs: 2 worker processes) and on the process pool.

The end-to-end manifest: 3 tiny synthetic scenes (48x32, 8 frames; s1 trains longer, so that a
worker can be killed mid-training) and one corrupt scene, through all five stages.  A thread
SIGKILLs the process that holds s1's run folder lock (RUN/.lock holds the writer's pid) once a
checkpoint exists; the task must be retried and resume from that checkpoint.  The Ray tests skip
when Ray is not installed; the pool tests always run.  80-90 s in all on 2 busy cores.
"""
from __future__ import annotations

import contextlib
import io
import json
import os
import signal
import threading
import time
from pathlib import Path

import pytest

from endowave_cl.batch import tasks as T
from endowave_cl.batch.manifest import load_manifest
from endowave_cl.errors import EndowaveError

KILLED_SCENE = "s1"
KILLED_ITERATIONS = 200     # s1's steps: several seconds of training, so the kill lands mid-way

MANIFEST = f"""
root = "{{root}}"
stages = ["flow", "train", "eval", "render", "export"]
scenes = ["data/s*", "data/bad"]

[resources]
cpus = 1
retries = 2

[settings]
iterations = 20
init_points = 500
eval_every = 0
log_every = 5

[overrides."{KILLED_SCENE}"]
iterations = {KILLED_ITERATIONS}
checkpoint_every = 20

[eval]
fps_runs = 0

[render]
video = false

[export]
time = 0.5
"""


# ------------------------------------------------------------------------------ manifest errors
def _write(tmp_path, text, name="m.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.fixture()
def two_scene_dirs(tmp_path):
    for n in ("a", "b"):
        (tmp_path / "data" / n).mkdir(parents=True)
    return tmp_path


@pytest.mark.parametrize("text, needle", [
    ('scenes = ["data/*"]', "key 'root'"),
    ('root = "o"', "key 'scenes' is missing"),
    ('root = "o"\nscenes = ["nothing/*"]', "'nothing/*' matches no folder"),
    ('root = "o"\nscenes = ["data/*"]\nstage = ["train"]', "unknown key 'stage'"),
    ('root = "o"\nscenes = ["data/*"]\nstages = ["train", "evaluate"]', "unknown stage 'evaluate'"),
    ('root = "o"\nscenes = ["data/*"]\nstages = []', "key 'stages'"),
    ('root = "o"\nscenes = ["data/*"]\n[settings]\nitertions = 3', "[settings]: unknown key 'itertions'"),
    ('root = "o"\nscenes = ["data/*"]\n[settings]\niterations = -1', "key 'iterations' must be at least 0"),
    ('root = "o"\nscenes = ["data/*"]\n[overrides.c]\niterations = 3', "key 'overrides.c' matches no scene"),
    ('root = "o"\nscenes = ["data/*"]\n[overrides.a]\nlr_opacity = "x"', "key 'lr_opacity' expects float"),
    ('root = "o"\nscenes = ["data/*"]\n[resources]\ncpus = "2"', "key 'resources.cpus' expects number"),
    ('root = "o"\nscenes = ["data/*"]\n[resources]\ncpus = 0', "key 'resources.cpus' must be > 0"),
    ('root = "o"\nscenes = ["data/*"]\n[resources]\nretries = -1', "'resources.retries' must be >= 0"),
    ('root = "o"\nscenes = ["data/*"]\n[resources]\nmemory = 3', "unknown key 'resources.memory'"),
    ('root = "o"\nscenes = ["data/*"]\n[eval]\nfps_runs = true', "key 'eval.fps_runs' expects integer"),
    ('root = "o"\nscenes = ["data/*"]\n[export]\ntime = 2', "key 'export.time' must be in [0, 1]"),
    ('root = "o"\nscenes = ["data/*", "other/a"]', "two scenes are named 'a'"),
    ('root = "o"\nscenes = ["data/*"\n', "not valid TOML"),
])
def test_bad_manifest_is_one_line_naming_the_file_and_key(two_scene_dirs, text, needle):
    (two_scene_dirs / "other" / "a").mkdir(parents=True)
    p = _write(two_scene_dirs, text)
    with pytest.raises(EndowaveError) as e:
        load_manifest(p)
    msg = str(e.value)
    assert needle in msg and str(p) in msg and "\n" not in msg


def test_cli_reports_a_bad_manifest_in_one_line(two_scene_dirs, capsys):
    from endowave_cl import cli
    p = _write(two_scene_dirs, 'root = "o"\nscenes = ["data/*"]\n[settings]\nnope = 1')
    assert cli.main(["batch", str(p)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"endowave-cl batch: error: {p} [settings]: unknown key 'nope'"]


def test_manifest_paths_overrides_and_defaults(two_scene_dirs):
    p = _write(two_scene_dirs, 'root = "out"\nscenes = ["data/*", "data/missing"]\n'
                               '[settings]\niterations = 7\n[overrides."b*"]\niterations = 9\nseed = 3\n')
    m = load_manifest(p)
    assert m.root == two_scene_dirs / "out"
    assert m.stages == ("flow", "train", "eval")
    assert [s.name for s in m.scenes] == ["a", "b", "missing"]    # a missing folder fails alone, later
    assert [s.settings for s in m.scenes] == [{"iterations": 7}, {"iterations": 9, "seed": 3}, {"iterations": 7}]
    assert m.resources == {"cpus": 1, "gpus": 0, "retries": 2, "device": None}


def test_train_completion_from_the_run_folder_files(two_scene_dirs):
    """Done when train_log.json has 'final' and the record's settings match; only iterations
    changed: continue (resume); other settings changed: start over."""
    from endowave_cl.atomic import write_json_atomic
    p = _write(two_scene_dirs, 'root = "out"\nscenes = ["data/a"]\n[settings]\niterations = 7\n')
    m = load_manifest(p)
    sc, run = m.scenes[0], m.root / "a"
    assert T.stage_status(m, sc, "train", run)[0] == "todo"
    write_json_atomic(run / "train_log.json", {"final": {"step": 7}, "history": []})
    write_json_atomic(T.record(run, "train"), {"options": T.stage_options(m, sc, "train"), "token": "x"})
    assert T.stage_status(m, sc, "train", run)[:3] == ("done", "trained, 7 steps", False)
    assert T.stage_status(m, sc, "train", run, force=True)[2] is True
    sc.settings["iterations"] = 9
    assert T.stage_status(m, sc, "train", run)[0::2] == ("todo", False)
    sc.settings["seed"] = 4
    assert T.stage_status(m, sc, "train", run)[0::2] == ("todo", True)
    # eval: complete only for the model it ran on
    write_json_atomic(run / "eval.json", {})
    write_json_atomic(T.record(run, "eval"), {"options": T.stage_options(m, sc, "eval"), "model": "x"})
    assert T.stage_status(m, sc, "eval", run)[0] == "done"
    write_json_atomic(T.record(run, "train"), {"options": T.stage_options(m, sc, "train"), "token": "y"})
    assert T.stage_status(m, sc, "eval", run)[:2] == ("todo", "the model changed")


def test_without_ray_the_pool_is_used_and_address_is_refused(monkeypatch, two_scene_dirs):
    from endowave_cl.batch import executors
    monkeypatch.setattr(executors, "ray_available", lambda: False)
    res = {"cpus": 1, "gpus": 0, "retries": 2, "device": None}
    said = []
    ex = executors.make_executor("auto", None, res, cpus=2, log=said.append)
    assert isinstance(ex, executors.PoolExecutor) and ex.workers == 2 and "process pool" in said[0]
    with pytest.raises(EndowaveError, match=r"Ray is not installed: pip install 'endowave-cl\[cluster\]'"):
        executors.make_executor("auto", "ray://head:10001", res)


# ------------------------------------------------------------------------------ end to end
@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """data/s0..s2 (synthetic, 48x32, 8 frames) and data/bad (a frame that is not a PNG)."""
    from endowave_cl.data.synth import make_synthetic_scene
    base = tmp_path_factory.mktemp("batch")
    for i in range(3):
        make_synthetic_scene(base / "data" / f"s{i}", width=48, height=32, frames=8, seed=i)
    make_synthetic_scene(base / "data" / "bad", width=48, height=32, frames=8, seed=9)
    (base / "data" / "bad" / "images" / "000003.png").write_bytes(b"not a png")
    return base


def _manifest(base: Path, root: str):
    return load_manifest(_write(base, MANIFEST.format(root=root), name=f"{root}.toml"))


class Killer(threading.Thread):
    """SIGKILLs the process training ``run_dir`` (the pid in RUN/.lock) once a checkpoint exists."""

    def __init__(self, run_dir: Path, timeout: float = 1800.0):
        # a long limit: on a loaded machine s1's training can start minutes into the batch; the
        # batch's end stops the thread (``done``)
        super().__init__(daemon=True)
        self.run_dir, self.timeout = run_dir, timeout
        self.pid = None
        self.step = None
        self.done = threading.Event()

    def run(self):
        end = time.monotonic() + self.timeout
        while time.monotonic() < end and self.pid is None and not self.done.is_set():
            cks = T.read_json(self.run_dir / "train_log.json") if list(self.run_dir.glob("checkpoint_*.npz")) else None
            lock = self.run_dir / ".lock"
            if cks is not None and lock.exists():
                with contextlib.suppress(OSError, ValueError):
                    pid = int(lock.read_text().strip())
                    if pid != os.getpid():          # never this test process
                        os.kill(pid, signal.SIGKILL)
                        self.pid = pid
                        self.step = max(int(p.name[11:18]) for p in self.run_dir.glob("checkpoint_*.npz"))
                        return
            time.sleep(0.02)


def _run(m, executor):
    from endowave_cl.batch.runner import run_batch
    killer = Killer(m.root / KILLED_SCENE)
    killer.start()
    out = io.StringIO()
    res = run_batch(m, executor, out=out, interval=1.0)
    killer.done.set()
    killer.join(timeout=1)
    return res, killer, out.getvalue()


@pytest.fixture(scope="module")
def ray_cluster():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)     # 2 worker processes at a time
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def ray_run(dataset, ray_cluster):
    from endowave_cl.batch.executors import RayExecutor
    m = _manifest(dataset, "out-ray")
    res, killer, text = _run(m, RayExecutor(None, None, m.resources))
    return m, res, killer, text


@pytest.fixture(scope="module")
def pool_run(dataset):
    from endowave_cl.batch.executors import PoolExecutor
    m = _manifest(dataset, "out-pool")
    res, killer, text = _run(m, PoolExecutor(2, m.resources))
    return m, res, killer, text


def _check_complete_run(m, res, text):
    rep = json.loads((m.root / "report.json").read_text())
    rows = {r["scene"]: r for r in rep["scenes"]}
    assert [rows[f"s{i}"]["status"] for i in range(3)] == ["done"] * 3, text
    for i in range(3):
        run = m.root / f"s{i}"
        r = rows[f"s{i}"]
        assert r["steps"] == (KILLED_ITERATIONS if f"s{i}" == KILLED_SCENE else 20)
        assert r["gaussians"] > 0 and r["device"] and r["train_seconds"] is not None
        for k in ("psnr", "psnr_masked", "ssim", "mean_psnr", "dis_psnr", "margin_psnr"):
            assert isinstance(r[k], float), (k, r)
        assert json.loads((run / "eval.json").read_text())["step"] == r["steps"]
        assert list((run / "render" / "frames").glob("*.png")) and (run / "model_t0.500.ply").is_file()
        # nothing half-written: no temporaries, no set-aside checkpoints, no lock left behind
        leftovers = [p for p in run.rglob("*") if p.name.endswith(".tmp") or p.name.endswith(".corrupt")
                     or ".tmp." in p.name or p.name == ".lock"]
        assert not leftovers, leftovers
    mean = rep["mean"]
    assert mean["scene"] == "mean (3 scenes)"
    assert mean["psnr"] == pytest.approx(sum(rows[f"s{i}"]["psnr"] for i in range(3)) / 3)
    csv_lines = (m.root / "report.csv").read_text().splitlines()
    assert len(csv_lines) == 1 + 4 + 2 and csv_lines[-2].startswith("mean (3 scenes),mean,")
    assert csv_lines[-1].startswith("std (3 scenes),std,")
    md = (m.root / "report.md").read_text()
    assert "| **mean (3 scenes)** |" in md and "| s0 |" in md
    return rows


def _check_killed_and_resumed(m, res, killer, text):
    assert killer.pid is not None, f"training of {KILLED_SCENE} ended before it could be killed\n{text}"
    run = m.root / KILLED_SCENE
    result = next(t.result for t in res.tasks.values() if (t.scene, t.stage) == (KILLED_SCENE, "train"))
    assert result["ok"] and result["attempt"] == 2 and result["pid"] != killer.pid, result
    log = (T.batch_dir(run) / "train.log").read_text()
    assert "attempt 2" in log and f"resuming from {run}/checkpoint_" in log, log
    resumed_at = int(log.split(f"resuming from {run}/checkpoint_")[1][:7])
    assert resumed_at >= killer.step > 0        # from the newest checkpoint, not from scratch
    hist = json.loads((run / "train_log.json").read_text())["history"]
    steps = [h["step"] for h in hist]
    assert steps == sorted(set(steps)) and steps[-1] == KILLED_ITERATIONS   # one history, no gap or repeat


def _check_corrupt_alone(m, res):
    rep = json.loads((m.root / "report.json").read_text())
    bad = next(r for r in rep["scenes"] if r["scene"] == "bad")
    assert bad["status"] == "failed" and "000003.png" in bad["error"] and "\n" not in bad["error"]
    assert res.failed_scenes == ["bad"]
    assert rep["counts"] == {"done": 3, "failed": 1, "incomplete": 0}
    assert "- bad: failed: endowave-cl flow: error:" in (m.root / "report.md").read_text()


def test_ray_runs_the_manifest_end_to_end(ray_run):
    m, res, killer, text = ray_run
    _check_complete_run(m, res, text)


def test_ray_killed_worker_is_retried_and_resumes(ray_run):
    _check_killed_and_resumed(*ray_run)


def test_ray_corrupt_scene_fails_alone(ray_run):
    m, res, _, _ = ray_run
    _check_corrupt_alone(m, res)


def test_ray_second_run_does_no_work(ray_run):
    from endowave_cl.batch.executors import RayExecutor
    from endowave_cl.batch.runner import run_batch
    m = ray_run[0]
    before = {p: p.stat().st_mtime_ns for p in m.root.rglob("*") if p.is_file()}
    res = run_batch(m, RayExecutor(None, None, m.resources), out=io.StringIO())
    assert res.ran == []
    after = {p: p.stat().st_mtime_ns for p in m.root.rglob("*") if p.is_file()}
    changed = sorted(str(p.relative_to(m.root)) for p in after if before.get(p) != after[p])
    assert changed == ["report.csv", "report.json", "report.md"]      # rewritten ...
    assert json.loads((m.root / "report.json").read_text()) == res.report  # ... with the same content


def test_pool_runs_the_same_manifest_with_the_same_report(pool_run, request):
    m, res, killer, text = pool_run
    rows = _check_complete_run(m, res, text)
    _check_killed_and_resumed(m, res, killer, text)
    _check_corrupt_alone(m, res)
    try:
        request.getfixturevalue("ray_cluster")
    except pytest.skip.Exception:
        return                                   # no Ray to compare with: the pool checks above stand
    ray_rows = {r["scene"]: r for r in json.loads((request.getfixturevalue("ray_run")[0].root
                                                   / "report.json").read_text())["scenes"]}
    for name, r in rows.items():
        for k, v in r.items():
            if k in ("train_seconds",):           # wall time differs from run to run
                continue
            if isinstance(v, float):
                assert v == pytest.approx(ray_rows[name][k], rel=1e-6, abs=1e-9), (name, k)
            else:
                assert v == ray_rows[name][k], (name, k)


def test_progress_is_read_from_the_task_log(tmp_path):
    """The per-scene progress line comes from the newest plain progress line of the current attempt."""
    from endowave_cl.batch.runner import train_progress
    d = T.batch_dir(tmp_path)
    d.mkdir(parents=True)
    line = "train: 300/1500 it (20%), 11.2 it/s, 1m47s left, loss=0.0412 psnr=27.31 N=500\n"
    (d / "train.log").write_text("== batch x: attempt 1\n" + line)
    assert train_progress(tmp_path) == {"step": 300, "total": 1500, "pct": 20, "eta": "1m47s", "psnr": 27.31}
    (d / "train.log").write_text("== batch x: attempt 1\n" + line + "== batch x: attempt 2\n")
    assert train_progress(tmp_path) is None       # a new attempt: the old figures are not its progress
