"""Hostile-user sweep over every command of the CLI (issue 57): hundreds of damaged inputs, junk
options and environment variables, foreign and damaged run folders, signals at random moments.

    python tools/sweep_cli.py [--seed 0] [--cases 320] [--out sweep.json] [--only train,eval]

Contract checked for each case (a violation is a defect):
  * exit 0, 1, 2 (argparse usage), 130 / 143 (signals); never a traceback or an "unexpected" error;
  * exit 1: exactly one error line (warning: / note: lines aside), starting "endowave-cl";
  * a case marked as bad input must not exit 0 (silently accepted);
  * the shared run and scene the cases start from are never changed (only a case's own copies);
  * no case takes longer than its time limit (a hang), and no hidden temporary is left behind.
Most cases run in this process (cli.main, SIGALRM as a time limit); signal cases run as a child.
Not part of the test suite: the cases that found a defect are tests in tests/cli/test_hostile.py.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

JUNK_NUMBERS = ["nan", "inf", "-inf", "-1", "0", "-0", "1e300", "-1e300", "1e-300", "abc", "", "0x10", "1_000",
                "99999999999999999999", "3.5"]
ENV_JUNK = {"ENDOWAVE_RASTER_VW": ["junk", "3", "-4", "16.0"], "ENDOWAVE_PROJECT_VW": ["x", "5"],
            "ENDOWAVE_RASTER_VARIANT": ["fast", "1"], "ENDOWAVE_PROJECT_VARIANT": ["both"],
            "ENDOWAVE_RASTER_BW": ["3", "zero"], "ENDOWAVE_PROGRESS": ["loud", "1"],
            "ENDOWAVE_PROGRESS_INTERVAL": ["soon", "-1", "nan", "inf"], "ENDOWAVE_PROBE_TIMEOUT": ["0", "x"],
            "ENDOWAVE_PROBE_PLANT": ["16=boom", "x"], "ENDOWAVE_NO_SELECT": ["maybe"], "ENDOWAVE_OCLGRIND": ["2"],
            "ENDOWAVE_CL_NO_DISK_CACHE": ["please"], "ENDOWAVE_CL_DEBUG": ["perhaps"]}


class Timeout(BaseException):   # not caught by the CLI's handlers
    pass


def _alarm(signum, frame):
    raise Timeout()


def snapshot(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and not p.name.startswith(".lock")} if folder.exists() else {}


def hidden_temporaries(folder: Path) -> list:
    from endowave_cl.atomic import TEMP_RE
    return [str(p) for p in folder.rglob(".*") if TEMP_RE.match(p.name)] if folder.exists() else []


class Sweep:
    def __init__(self, root: Path, seed: int):
        self.root, self.rng = root, random.Random(seed)
        self.cases, self.results = [], []

    # ------------------------------------------------------------------ fixtures
    def setup(self):
        from endowave_cl import cli
        from endowave_cl.data.synth import make_synthetic_scene
        self.scene = self.root / "base_scene"
        make_synthetic_scene(self.scene, width=48, height=32, frames=10, seed=3)
        self.run = self.root / "base_run"
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()) as err:
            rc = cli.main(["train", str(self.scene), "--out", str(self.run), "--iterations", "2", "--quiet",
                           "--no-flow", "--set", "init_points=100"])
        assert rc == 0, err.getvalue()
        self.protected = {"scene": snapshot(self.scene), "run": snapshot(self.run)}

    def work(self) -> Path:
        return Path(tempfile.mkdtemp(prefix="case-", dir=self.root))

    def scene_copy(self, w: Path) -> Path:
        shutil.copytree(self.scene, w / "scene")
        return w / "scene"

    def run_copy(self, w: Path, scene=None) -> Path:
        shutil.copytree(self.run, w / "run")
        if scene is not None:
            cfg = json.loads((w / "run" / "config.json").read_text())
            cfg["scene"] = str(scene)
            (w / "run" / "config.json").write_text(json.dumps(cfg))
        return w / "run"

    # ------------------------------------------------------------------ case makers
    def add(self, name, argv_fn, bad=True, env=None, limit=120, child=None):
        """argv_fn(work) -> argv; bad: the input is invalid (exit 0 would be a silent acceptance)."""
        self.cases.append(dict(name=name, argv_fn=argv_fn, bad=bad, env=env or {}, limit=limit, child=child))

    def build(self):
        r = self.rng
        S, R = lambda w: str(self.scene), lambda w: str(self.run)
        # numeric options of every command, junk values
        T = ["--iterations", "2", "--quiet", "--no-flow", "--set", "init_points=50"]
        opts = [("train", "--iterations", lambda w: ["train", S(w), "--out", str(w / "r"), "--quiet", "--no-flow"]),
                ("train", "--minutes", lambda w: ["train", S(w), "--out", str(w / "r")] + T),
                ("train", "--downscale", lambda w: ["train", S(w), "--out", str(w / "r")] + T),
                ("flow", "--downscale", lambda w: ["flow", S(w), "--cache-dir", str(w / "c"), "--no-progress"]),
                ("flow", "--max-pixels", lambda w: ["flow", S(w), "--cache-dir", str(w / "c"), "--no-progress"]),
                ("eval", "--fps-runs", lambda w: ["eval", str(self.run_copy(w)), "--no-baselines"]),
                ("render", "--fps", lambda w: ["render", str(self.run_copy(w))]),
                ("export", "--time", lambda w: ["export", R(w), "--out", str(w / "m.ply")]),
                ("synth", "--width", lambda w: ["synth", str(w / "s"), "--frames", "3"]),
                ("synth", "--frames", lambda w: ["synth", str(w / "s"), "--width", "32", "--height", "24"]),
                ("synth", "--seed", lambda w: ["synth", str(w / "s"), "--frames", "3", "--width", "32", "--height", "24"]),
                ("synth", "--deformation", lambda w: ["synth", str(w / "s"), "--frames", "3", "--width", "32",
                                                      "--height", "24"]),
                ("view", "--port", lambda w: ["view", str(w / "norun")])]
        # the values each option accepts (the others must be refused); SKIP: valid but asks for hours
        valid = {"--iterations": {"1_000"}, "--minutes": {"1e-300"}, "--max-pixels": {"0", "-0", "1_000",
                 "99999999999999999999"}, "--fps-runs": {"0", "-0", "1_000"}, "--fps": {"3.5", "1_000"},
                 "--time": {"0", "-0", "1e-300"}, "--width": {"1_000"}, "--frames": {"1_000"},
                 "--seed": {"0", "-0", "1_000"}, "--deformation": {"0", "-0", "1e-300"}}
        maybe = {"--deformation": {"3.5"}}      # may fold the tissue at this seed: refused or not
        skip = {"--iterations": {"99999999999999999999"}, "--minutes": {"1e300", "99999999999999999999", "1_000", "3.5"}}
        for cmd, opt, base in opts:
            for v in JUNK_NUMBERS:
                if v in skip.get(opt, ()):
                    continue
                bad = None if v in maybe.get(opt, ()) else v not in valid.get(opt, set())
                self.add(f"{cmd} {opt}={v!r}", (lambda b, o, val: lambda w: b(w) + [o, val])(base, opt, v),
                         bad=bad, limit=180)
        # --set keys with junk values
        keys = ["iterations", "downscale", "flow_max_pixels", "lambda_flow", "sh_degree", "init_points", "seed",
                "lr_opacity", "densify_every", "no_such_key", "flow_method", "split", "recipe"]
        for _ in range(40):
            k, v = r.choice(keys), r.choice(JUNK_NUMBERS + ["dis", "test"])
            self.add(f"train --set {k}={v!r}", (lambda k, v: lambda w: ["train", S(w), "--out", str(w / "r"),
                                                                        "--set", f"{k}={v}", "--iterations", "2",
                                                                        "--quiet", "--no-flow"])(k, v),
                     bad=None)
        # environment variables
        for name, values in ENV_JUNK.items():
            for v in values:
                cmd = r.choice([["export", "RUN"], ["eval", "RUN", "--fps-runs", "0", "--no-baselines"],
                                ["devices"], ["synth", "OUT", "--frames", "3"]])
                self.add(f"env {name}={v!r} {cmd[0]}",
                         (lambda c: lambda w: [str(self.run_copy(w)) if a == "RUN" else str(w / "s") if a == "OUT"
                                               else a for a in c])(cmd), env={name: v})
        # scene damage, for train / flow / eval --scene
        damages = ["truncate_image", "truncate_depth", "truncate_mask", "resize_image", "delete_mask", "pose_nan",
                   "pose_rows", "scene_json_text", "depth_scale_tiny", "depth_scale_huge", "depth_scale_inf",
                   "depth_scale_bool", "mask_all_tool_test", "mask_all_tool", "black_depth", "unpadded_names",
                   "gt_flow_shape", "gt_flow_nan", "gt_flow_huge", "user_flow_huge", "user_flow_small",
                   "user_flow_text", "empty_images", "images_is_file", "symlink_loop"]
        for dmg in damages:
            for cmd in ("train", "flow", "eval"):
                self.add(f"{cmd} on scene damage {dmg}", (lambda d, c: lambda w: self.damaged(w, d, c))(dmg, cmd),
                         bad=dmg not in ("unpadded_names", "symlink_loop")     # a loop is no file: not a frame
                         and not (dmg.startswith("mask_all_tool") and cmd == "flow")  # flow scores no frame
                         and not (dmg.startswith("user_flow") and cmd == "eval")
                         and not (dmg == "user_flow_small" and cmd != "eval") and not (dmg == "black_depth" and cmd == "flow")
                         and not (dmg.startswith("gt_flow") and cmd == "flow" and False),
                         limit=180)
        # run folder damage, every command that opens a run
        rdamages = ["ckpt_truncated", "ckpt_bitflip", "ckpt_all_corrupt", "config_junk", "config_list", "config_missing",
                    "config_scene_missing", "config_downscale_junk", "log_junk", "other_scene", "scene_regenerated",
                    "no_checkpoint", "run_is_file", "world_scale_junk"]
        for dmg in rdamages:
            for cmd in ("eval", "render", "export", "train", "view"):
                if cmd == "view" and dmg in ("ckpt_truncated", "ckpt_bitflip", "log_junk"):
                    continue             # the viewer would open these (an older checkpoint) and serve
                self.add(f"{cmd} on run damage {dmg}", (lambda d, c: lambda w: self.damaged_run(w, d, c))(dmg, cmd),
                         # export reads the checkpoint alone; train writes config.json anew
                         bad=dmg not in ("ckpt_truncated", "ckpt_bitflip", "log_junk")
                         and not (cmd == "export" and dmg.startswith("config_"))
                         and not (cmd == "train" and dmg in ("config_missing", "config_scene_missing",
                                                             "config_downscale_junk")), limit=180)
        # foreign --out folders and data-loss sequences
        for what in ("user_config", "user_log", "file_out", "nested_in_file", "restart_twice_killed"):
            self.add(f"train --out {what}", (lambda x: lambda w: self.foreign_out(w, x))(what), bad=None)
        # batch manifests
        mjunk = ['[resources]\ncpus = 1e300', '[resources]\ncpus = 0', '[resources]\ncpus = "x"', '[resources]\ngpus = -1',
                 '[resources]\nretries = -1', '[render]\nfps = 1e9', '[render]\nfps = 0', '[export]\ntime = 2',
                 '[eval]\nfps_runs = -1', '[settings]\niterations = -1', '[settings]\nnope = 1', 'stages = ["x"]',
                 'stages = []', '[resources]\ncpus = 1e-300', 'scenes = ["nothing/*"]', '[settings]\ndownscale = 0.5',
                 '[settings]\nflow_max_pixels = 20', '[overrides.zzz]\niterations = 3']
        for t in mjunk:
            self.add(f"batch manifest {t!r}", (lambda t: lambda w: self.manifest(w, t))(t))
        # paths: missing, unicode, long, file-for-folder
        for cmd in ("train", "flow", "eval", "render", "export", "view", "batch"):
            for p in ("missing", "file", "unicode", "long"):
                self.add(f"{cmd} path {p}", (lambda c, p: lambda w: self.path_case(w, c, p))(cmd, p),
                         bad=p in ("missing", "file", "long"))
        # signals at random moments (children)
        for i in range(24):
            cmd = r.choice(["train", "eval", "synth", "flow", "export"])
            delay = round(r.uniform(0.05, 6.0), 2)
            sig = r.choice([signal.SIGINT, signal.SIGTERM])
            self.add(f"{cmd} {signal.Signals(sig).name} after {delay}s",
                     (lambda c: lambda w: self.signal_argv(w, c))(cmd), bad=None, child=(sig, delay), limit=240)

    # ------------------------------------------------------------------ case bodies
    def damaged(self, w, dmg, cmd):
        import cv2
        s = self.scene_copy(w)
        f = lambda sub, i: sorted((s / sub).glob("*.png"))[i]
        if dmg.startswith("truncate_"):
            p = f({"image": "images", "depth": "depth", "mask": "masks"}[dmg.split("_")[1]], 3)
            p.write_bytes(p.read_bytes()[:40])
        elif dmg == "resize_image":
            p = f("images", 0)
            cv2.imwrite(str(p), np.zeros((10, 20, 3), np.uint8))
        elif dmg == "delete_mask":
            f("masks", 2).unlink()
        elif dmg == "pose_nan":
            a = np.load(s / "poses_bounds.npy")
            a[2, 3] = np.nan
            np.save(s / "poses_bounds.npy", a)
        elif dmg == "pose_rows":
            np.save(s / "poses_bounds.npy", np.load(s / "poses_bounds.npy")[:4])
        elif dmg == "scene_json_text":
            (s / "scene.json").write_text("{oops")
        elif dmg.startswith("depth_scale_"):
            info = json.loads((s / "scene.json").read_text())
            info["depth_scale"] = {"tiny": 1e-300, "huge": 1e300, "inf": float("inf"), "bool": True}[dmg.split("_")[2]]
            (s / "scene.json").write_text(json.dumps(info))
        elif dmg.startswith("mask_all_tool"):
            for i, p in enumerate(sorted((s / "masks").glob("*.png"))):
                if dmg == "mask_all_tool" or i in (1, 9):
                    cv2.imwrite(str(p), np.full((32, 48), 255, np.uint8))
        elif dmg == "black_depth":
            p = f("depth", 4)
            cv2.imwrite(str(p), np.zeros((32, 48), np.uint16))
        elif dmg == "unpadded_names":
            for sub in ("images", "depth", "masks"):
                for p in (s / sub).glob("*.png"):
                    p.rename(p.with_name(f"{int(p.stem)}.png"))
            shutil.rmtree(s / "gt_flow")
        elif dmg.startswith("gt_flow_"):
            v = {"shape": np.zeros((5, 5, 2)), "nan": np.full((32, 48, 2), np.nan),
                 "huge": np.full((32, 48, 2), 1e30)}[dmg.split("_")[2]]
            np.save(s / "gt_flow" / "000001.npy", v.astype(np.float32))
            np.save(s / "gt_flow" / "000002.npy", v.astype(np.float32))
        elif dmg.startswith("user_flow_"):
            (s / "flow").mkdir()
            names = [p.stem for p in sorted((s / "images").glob("*.png"))]
            train = [i for i in range(10) if (i - 1) % 8]
            for k, k2 in zip(train[:-1], train[1:]):
                val = {"huge": np.full((32, 48, 2), 1e30), "small": np.zeros((16, 24, 2)),
                       "text": np.array([["a"]])}[dmg.split("_")[2]]
                np.save(s / "flow" / f"{names[k]}_{names[k2]}.npy", val)
        elif dmg == "empty_images":
            for p in (s / "images").glob("*.png"):
                p.unlink()
        elif dmg == "images_is_file":
            shutil.rmtree(s / "images")
            (s / "images").write_text("x")
        elif dmg == "symlink_loop":
            (s / "depth" / "loop.png").symlink_to(s / "depth" / "loop.png")
        if cmd == "train":
            return ["train", str(s), "--out", str(w / "r"), "--iterations", "2", "--quiet", "--set", "init_points=100"]
        if cmd == "flow":
            return ["flow", str(s), "--cache-dir", str(w / "c"), "--no-progress"]
        return ["eval", str(self.run_copy(w)), "--scene", str(s), "--fps-runs", "0", "--no-baselines"]

    def damaged_run(self, w, dmg, cmd):
        from endowave_cl.data.synth import make_synthetic_scene
        s = self.scene_copy(w)
        run = self.run_copy(w, scene=s)
        ck = sorted(run.glob("checkpoint_*.npz"))
        if dmg == "ckpt_truncated":
            shutil.copy(ck[-1], run / "checkpoint_0000001.npz")
            b = ck[-1].read_bytes()
            (run / "checkpoint_0000009.npz").write_bytes(b[: len(b) // 2])
        elif dmg == "ckpt_bitflip":
            shutil.copy(ck[-1], run / "checkpoint_0000001.npz")
            b = bytearray(ck[-1].read_bytes())
            b[len(b) // 2] ^= 0x10
            (run / "checkpoint_0000009.npz").write_bytes(bytes(b))
        elif dmg == "ckpt_all_corrupt":
            for p in ck:
                p.write_bytes(b"junk")
        elif dmg == "config_junk":
            (run / "config.json").write_text("{junk")
        elif dmg == "config_list":
            (run / "config.json").write_text("[1]")
        elif dmg == "config_missing":
            (run / "config.json").unlink()
        elif dmg == "config_scene_missing":
            cfg = json.loads((run / "config.json").read_text())
            cfg["scene"] = str(w / "gone")
            (run / "config.json").write_text(json.dumps(cfg))
        elif dmg == "config_downscale_junk":
            cfg = json.loads((run / "config.json").read_text())
            cfg["downscale"] = -3
            (run / "config.json").write_text(json.dumps(cfg))
        elif dmg == "log_junk":
            (run / "train_log.json").write_text("{junk")
        elif dmg == "other_scene":
            make_synthetic_scene(w / "other", width=48, height=32, frames=10, seed=4)
            cfg = json.loads((run / "config.json").read_text())
            cfg["scene"] = str(w / "other")
            (run / "config.json").write_text(json.dumps(cfg))
            s = w / "other"
        elif dmg == "scene_regenerated":
            make_synthetic_scene(s, width=48, height=32, frames=10, seed=8, force=True)
        elif dmg == "no_checkpoint":
            for p in ck:
                p.unlink()
        elif dmg == "run_is_file":
            shutil.rmtree(run)
            run.write_text("x")
        elif dmg == "world_scale_junk":
            from endowave_cl.checkpoint import load_checkpoint, save_checkpoint
            d = load_checkpoint(ck[-1])
            d["extra"]["world_scale"] = -1.0
            save_checkpoint(ck[-1], d["gaussians"], d["adam_state"], d["step"], d["config"], d["extra"])
        if cmd == "eval":
            return ["eval", str(run), "--fps-runs", "0", "--no-baselines"]
        if cmd == "render":
            return ["render", str(run), "--no-video"]
        if cmd == "export":
            return ["export", str(run), "--out", str(w / "m.ply")]
        if cmd == "view":
            return ["view", str(run), "--port", "18765"]
        return ["train", str(s), "--out", str(run), "--iterations", "3", "--quiet", "--no-flow"]

    def foreign_out(self, w, what):
        out = w / "mine"
        if what == "user_config":
            out.mkdir()
            (out / "config.json").write_text('{"my": "settings"}')
        elif what == "user_log":
            out.mkdir()
            (out / "train_log.json").write_text("my notes")
        elif what == "file_out":
            out.write_text("x")
        elif what == "nested_in_file":
            out.write_text("x")
            out = out / "deeper"
        elif what == "restart_twice_killed":
            run = self.run_copy(w)
            (run / "config.json").write_text((run / "config.json").read_text())
            from endowave_cl.train.run_folder import retire_previous_run
            retire_previous_run(run, log=lambda m: None)           # the first --restart, then killed
            cfg = json.loads((run / "previous_run" / "config.json").read_text())
            (run / "config.json").write_text(json.dumps(cfg))
            self._expect_kept = run / "previous_run" / "checkpoint_0000002.npz"
            return ["train", str(self.scene), "--out", str(run), "--restart", "--iterations", "1", "--quiet",
                    "--no-flow", "--set", "init_points=50", "--set", "checkpoint_every=0"]
        return ["train", str(self.scene), "--out", str(out), "--iterations", "2", "--quiet", "--no-flow"]

    def manifest(self, w, text):
        (w / "data").mkdir()
        shutil.copytree(self.scene, w / "data" / "a")
        m = w / "m.toml"
        body = text if text.startswith(("scenes", "stages")) else ""
        m.write_text(('root = "o"\n' + ('scenes = ["data/*"]\n' if not body.startswith("scenes") else "")
                      + (body + "\n" if body else "") + ("" if body else text) + "\n"))
        return ["batch", str(m), "--executor", "pool"]

    def path_case(self, w, cmd, p):
        target = {"missing": w / "nothing", "file": w / "afile", "unicode": w / "sc\u00e8ne \u2013 \U0001f600",
                  "long": w / ("x" * 300)}[p]
        if p == "file":
            target.write_text("x")
        if p == "unicode":
            if cmd in ("train", "flow"):
                shutil.copytree(self.scene, target)
            elif cmd in ("eval", "render", "export", "view"):
                shutil.copytree(self.run, target)
        if cmd == "train":
            return ["train", str(target), "--out", str(w / "r"), "--iterations", "2", "--quiet", "--no-flow",
                    "--set", "init_points=50"] if p != "unicode" else \
                ["train", str(target), "--out", str(w / "r \u00e9"), "--iterations", "2", "--quiet", "--no-flow",
                 "--set", "init_points=50"]
        if cmd == "flow":
            return ["flow", str(target), "--cache-dir", str(w / "c"), "--no-progress"]
        if cmd == "eval":
            return ["eval", str(target), "--fps-runs", "0", "--no-baselines"]
        if cmd == "render":
            return ["render", str(target), "--no-video"]
        if cmd == "export":
            return ["export", str(target)]
        if cmd == "view":
            return ["view", str(target), "--port", "-1"]
        return ["batch", str(target)]

    def signal_argv(self, w, cmd):
        if cmd == "train":
            return ["train", str(self.scene), "--out", str(w / "r"), "--iterations", "40", "--quiet", "--no-flow",
                    "--set", "init_points=200", "--set", "checkpoint_every=5"]
        if cmd == "eval":
            return ["eval", str(self.run_copy(w)), "--fps-runs", "3"]
        if cmd == "synth":
            return ["synth", str(w / "s"), "--width", "160", "--height", "128", "--frames", "24"]
        if cmd == "flow":
            return ["flow", str(self.scene), "--cache-dir", str(w / "c"), "--no-progress", "--method", "farneback"]
        return ["export", str(self.run_copy(w)), "--out", str(w / "m.ply")]

    # ------------------------------------------------------------------ running and judging
    def run_case(self, c) -> dict:
        from endowave_cl import cli
        w = self.work()
        self._expect_kept = None
        try:
            argv = c["argv_fn"](w)
        except Exception as e:  # noqa: BLE001
            return dict(name=c["name"], verdict="setup-error", detail=repr(e))
        old_env = {k: os.environ.get(k) for k in c["env"]}
        t0 = time.monotonic()
        if c["child"] is not None:
            sig, delay = c["child"]
            p = subprocess.Popen([sys.executable, "-m", "endowave_cl", *argv], stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True, env={**os.environ, **c["env"]}, cwd=str(w))
            time.sleep(delay)
            if p.poll() is None:
                p.send_signal(sig)
            try:
                out, err = p.communicate(timeout=c["limit"])
                rc = p.returncode
            except subprocess.TimeoutExpired:
                p.kill()
                out, err = p.communicate()
                rc = "timeout"
        else:
            os.environ.update(c["env"])
            out_b, err_b = io.StringIO(), io.StringIO()
            old = signal.signal(signal.SIGALRM, _alarm)
            signal.alarm(c["limit"])
            try:
                with contextlib.redirect_stdout(out_b), contextlib.redirect_stderr(err_b):
                    rc = cli.main(argv)
            except SystemExit as e:
                rc = e.code if isinstance(e.code, int) else 2
            except Timeout:
                rc = "timeout"
            except BaseException as e:  # noqa: BLE001
                rc, err_b = "raised", io.StringIO(err_b.getvalue() + f"Traceback (escaped): {e!r}")
            finally:
                signal.alarm(0)
                signal.signal(signal.SIGALRM, old)
                for k, v in old_env.items():
                    if v is None:
                        os.environ.pop(k, None)
                    else:
                        os.environ[k] = v
            out, err = out_b.getvalue(), err_b.getvalue()
        took = time.monotonic() - t0
        problems = self.judge(c, rc, out, err, w)
        res = dict(name=c["name"], argv=[str(a) for a in argv], rc=rc, seconds=round(took, 2),
                   verdict="ok" if not problems else "DEFECT", problems=problems,
                   stderr_tail=err.strip().splitlines()[-3:])
        shutil.rmtree(w, ignore_errors=True)
        return res

    def judge(self, c, rc, out, err, w) -> list:
        problems = []
        if rc == "timeout":
            problems.append(f"no result within {c['limit']} s (a hang)")
        elif rc == "raised":
            problems.append("an exception escaped cli.main")
        elif rc not in (0, 1, 2, 130, 143, -2, -15):
            problems.append(f"exit status {rc}")
        if "Traceback" in err:
            problems.append("traceback")
        if "unexpected" in err:
            problems.append("unexpected error")
        if rc == 1:
            lines = [ln for ln in err.strip().splitlines() if ln.strip() and not ln.startswith(("warning:", "note:"))
                     and not ln.startswith(("render:", "train:", "flow"))]
            if len(lines) != 1 or not lines[0].startswith("endowave-cl"):
                problems.append(f"not one error line: {lines[:3]}")
        if c["bad"] is True and rc == 0:
            problems.append("bad input accepted (exit 0)")
        if snapshot(self.scene) != self.protected["scene"]:
            problems.append("the shared scene changed")
            self.protected["scene"] = snapshot(self.scene)
        if snapshot(self.run) != self.protected["run"]:
            problems.append("the shared run changed")
            self.protected["run"] = snapshot(self.run)
        if self._expect_kept is not None and not self._expect_kept.is_file():
            problems.append(f"{self._expect_kept.name} of previous_run/ lost")
        if c["child"] is None and hidden_temporaries(w):
            problems.append(f"temporaries left: {hidden_temporaries(w)[:2]}")
        return problems


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cases", type=int, default=0, help="at most this many cases (0: all)")
    ap.add_argument("--only", default="", help="comma-separated words a case name must contain one of")
    ap.add_argument("--out", default="", help="write the results as JSON here")
    args = ap.parse_args()
    os.environ.setdefault("ENDOWAVE_PROGRESS", "off")
    root = Path(tempfile.mkdtemp(prefix="endowave-sweep-"))
    sw = Sweep(root, args.seed)
    try:
        sw.setup()
        sw.build()
        cases = [c for c in sw.cases if not args.only or any(w in c["name"] for w in args.only.split(","))]
        if args.cases:
            cases = cases[: args.cases]
        print(f"{len(cases)} cases", flush=True)
        for i, c in enumerate(cases):
            res = sw.run_case(c)
            sw.results.append(res)
            mark = "ok " if res["verdict"] == "ok" else "!! "
            print(f"{mark}{i + 1:4d} {res['name'][:70]:<70} rc={res.get('rc')} {res.get('seconds', '')}s "
                  f"{'; '.join(res.get('problems', [])) or ''} {res.get('detail', '')}", flush=True)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    bad = [r for r in sw.results if r["verdict"] != "ok"]
    print(f"\n{len(sw.results)} cases, {len(bad)} with a problem")
    for r in bad:
        print(f"  {r['name']}: {'; '.join(r.get('problems', []))} {r.get('detail', '')} | {r.get('stderr_tail')}")
    if args.out:
        Path(args.out).write_text(json.dumps(sw.results, indent=1))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
