"""Paper scale on one GPU in at most 9 minutes: benchmark rows, a wall-budget phase-1 run, its
evaluation and curves, all in one summary.json (issue #17).

Started by experiments/gpu/paper_scale.sh, which first installs the CUDA build of the pinned jax
and the project into a virtual environment and then runs this file with that environment's
Python. This file itself uses only the standard library: it must still write the summary when
the install failed. Every stage that needs JAX runs in a child process under its own time limit
(killed with its whole process group past it), so one stage that hangs cannot eat the others'
time, and the summary is rewritten (atomically) after every stage, so what finished survives a
later stage's failure or the whole script being killed.

Stages, in priority order; a stage that no longer fits the overall budget is skipped, and the
training run gets what is left (up to its target) after keeping time for the stages after it:

  devices               jax.devices(), versions, the first device's memory_stats(), the
                        provenance stamp of `nmjax.provenance` (CPU and GPU model, commit)
  data                  the synth-arm set (`nmjax prepare-data`), made before anything is timed
  bench_skel_f32        `nmjax bench`, phase 1 at G=64, C=128, K=28, batch 3 x T=10, float32
  bench_skel_f32_24gib  the same row with the GPU allocator capped at 24 GiB (the authors' GPU);
                        it loads the row's compiled program from the compilation cache
  bench_dyn_nm          phase 2 at B=16, T=20, S=10, D_z=128, D_h=512, K=28, model nm
  bench_dyn_vrnn        the same, the positional vrnn baseline
  bench_skel_bf16       phase 1 as bench_skel_f32 with bfloat16 convolutions
  train                 `nmjax train-skel --preset default` on synth-arm for a wall budget
                        (`--set time_limit_minutes=...`)
  evaluate              `nmjax evaluate` on that run (SC in both definitions, tracking CD, bones)
  curves                experiments/train_skel_curves.py on that run
  pack                  the run's artefacts, checkpoints left out, into OUT/run.tar.gz
  bench_skel_max_batch  phase 1 float32 at the largest batch that fits (estimated from the
                        B=3 row's memory, lowered until one runs)

OUT gets summary.json, run.tar.gz and curves.png (the shell script adds paper_scale.log): few
files, no folders, because the machine that runs this returns at most 8 files from OUT.

--dry-run runs the same stages on the CPU at the tiny preset (a 3-sequence data set, 2-step bench
rows, 4 training steps); tests/test_gpu_script.py runs it.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

GIB = 2**30
REPO = Path(__file__).resolve().parents[2]
DATA = "synth-arm"
# The GPU allocator may take this share of the device (JAX's default, 0.75, would leave the
# largest-batch row a quarter of the H200 short).
MEM_FRACTION = 0.95
RTX_3090_BYTES = 24 * GIB  # the authors' GPU (paper appendix B.2)
# The run folder's artefacts that travel back; checkpoints and TensorBoard files stay behind.
ARTEFACTS = (
    "config.json",
    "metrics.jsonl",
    "skeleton.json",
    "affinity.npy",
    "keypoint_stats.npz",
    "keypoints_train.npz",
    "keypoints_test.npz",
    "figures",
    "eval",
)
STAGES = (
    "devices",
    "data",
    "bench_skel_f32",
    "bench_skel_f32_24gib",
    "bench_dyn_nm",
    "bench_dyn_vrnn",
    "bench_skel_bf16",
    "train",
    "evaluate",
    "curves",
    "pack",
    "bench_skel_max_batch",
)
# Stages whose time is kept free while the stages before them run (their minimum seconds).
RESERVED = ("evaluate", "curves", "pack")

# The versions that actually ran (the machine's own where the pinned install was impossible) and
# any project dependency that cannot be imported, named before a later stage fails on it.
DEVICES_CODE = """
import importlib.metadata, importlib.util, json, sys
import jax
devices = jax.devices()
stats = devices[0].memory_stats() or {}
packages = ["jax", "jaxlib", "flax", "optax", "orbax-checkpoint", "grain", "numpy", "scipy",
            "matplotlib", "imageio", "tqdm", "tensorboardX", "trimesh", "rtree"]
versions = {}
for name in packages:
    try:
        versions[name] = importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        versions[name] = None
modules = ["flax", "optax", "orbax.checkpoint", "grain", "scipy", "matplotlib", "imageio", "tqdm",
           "tensorboardX", "trimesh", "rtree", "nmjax"]
info = {
    "backend": jax.default_backend(),
    "devices": [f"{d.platform}:{d.device_kind}" for d in devices],
    "device_count": len(devices),
    "bytes_limit": stats.get("bytes_limit"),
    "python": sys.version.split()[0],
    "versions": versions,
    "missing_modules": [m for m in modules if importlib.util.find_spec(m) is None],
}
try:  # the stamp every results file of the project carries (nmjax.provenance)
    from nmjax import provenance
    info["provenance"] = provenance.stamp()
except ImportError as err:
    info["provenance"] = f"not recorded: {err}"
print(json.dumps(info, indent=1))
with open(sys.argv[1], "w") as f:
    json.dump(info, f)
"""


@dataclasses.dataclass(frozen=True)
class Plan:
    """Sizes, step counts and time limits (seconds) of one mode (GPU or dry run)."""

    preset: str
    budget_s: float  # the whole script, install included
    data_args: tuple[str, ...]  # `nmjax prepare-data` options beyond --data and --root
    keypoints: int  # K of the bench rows (phase 1 and phase 2)
    skel_overrides: tuple[str, ...]  # extra `nmjax bench --set` items of the phase-1 rows
    skel_steps: tuple[int, int]  # (timed, warmup) steps of a phase-1 bench row
    dyn_steps: tuple[int, int]
    train_seconds: float  # target wall budget of the training loop (time_limit_minutes * 60)
    min_train_seconds: float  # less than this left: no training run
    train_overhead_s: float  # start-up, final validation and artefacts beyond the loop
    train_args: tuple[str, ...]
    eval_args: tuple[str, ...]
    max_batch_cap: int
    max_batch_tries: int
    limits: dict[str, float]  # the most a stage may take
    minimum: dict[str, float]  # the least worth starting it with
    env: dict[str, str]


GPU = Plan(
    preset="default",
    budget_s=540.0,
    data_args=(),
    keypoints=28,
    skel_overrides=(),
    skel_steps=(20, 3),
    dyn_steps=(50, 5),
    train_seconds=240.0,
    min_train_seconds=45.0,
    train_overhead_s=90.0,
    train_args=(),
    eval_args=(),
    max_batch_cap=64,
    max_batch_tries=2,
    limits={
        "devices": 60,
        "data": 150,
        "bench_skel_f32": 150,
        "bench_dyn_nm": 90,
        "bench_dyn_vrnn": 90,
        "bench_skel_bf16": 150,
        "evaluate": 120,
        "curves": 60,
        "pack": 30,
        "bench_skel_max_batch": 240,
        "bench_skel_f32_24gib": 120,
    },
    minimum={
        "devices": 20,
        "data": 30,
        "bench_skel_f32": 60,
        "bench_dyn_nm": 30,
        "bench_dyn_vrnn": 30,
        "bench_skel_bf16": 60,
        "evaluate": 60,
        "curves": 15,
        "pack": 5,
        "bench_skel_max_batch": 60,
        "bench_skel_f32_24gib": 30,
    },
    env={"XLA_PYTHON_CLIENT_MEM_FRACTION": str(MEM_FRACTION)},
)

# Generous limits: the test suite runs this on loaded 2-core machines, where a stage that is
# merely slow must not be cut.
DRY = dataclasses.replace(
    GPU,
    preset="tiny",
    budget_s=1800.0,
    data_args=("--sequences", "3", "--frames", "12", "--points", "1500"),
    keypoints=6,
    # G=8 instead of the tiny preset's 16: the same code path with fewer operations to compile.
    skel_overrides=("skel:data.grid=8", "skel:model.grid=8"),
    skel_steps=(2, 0),
    dyn_steps=(2, 0),
    train_seconds=300.0,
    min_train_seconds=30.0,
    train_overhead_s=300.0,
    # The bench rows' shapes, so that the training step loads their compiled program.
    train_args=("--steps", "4", "--set", "data.grid=8", "--set", "model.grid=8"),
    eval_args=("--max-crops", "2"),
    max_batch_cap=4,
    max_batch_tries=1,
    limits={name: 400.0 for name in GPU.limits},
    # The dry run checks the stages, not their speed: the test suite's cheaper CPU code
    # generation (tests/conftest.py says what each flag saves).
    env={
        "JAX_PLATFORMS": "cpu",
        "XLA_FLAGS": "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
        " --xla_cpu_use_fusion_emitters=false",
    },
)


# --- small pure helpers (tested) ----------------------------------------------------------------


def write_json_atomic(path: Path, obj: Any) -> None:
    """JSON to `path` through a temporary file and a rename: never half written."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(obj, f, indent=1, allow_nan=True)
            f.write("\n")
        os.chmod(tmp, 0o644)  # mkstemp makes it private
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def stage_limit(plan: Plan, name: str, now: float, deadline: float) -> float:
    """Seconds stage `name` may take now: its own limit, and no more than what is left before
    `deadline` once the minimum of every reserved stage after it is kept free."""
    later = STAGES[STAGES.index(name) + 1 :]
    reserve = sum(plan.minimum[s] for s in RESERVED if s in later)
    return min(plan.limits[name], deadline - now - reserve)


def train_seconds(plan: Plan, now: float, deadline: float) -> float | None:
    """The training loop's wall budget in seconds (config time_limit_minutes * 60): the target,
    or what remains after the reserved stages and the run's start-up and artefacts; None when
    that is too little."""
    later = STAGES[STAGES.index("train") + 1 :]
    reserve = sum(plan.minimum[s] for s in RESERVED if s in later)
    left = deadline - now - reserve - plan.train_overhead_s
    if left < plan.min_train_seconds:
        return None
    return min(plan.train_seconds, left)


def max_batch_candidates(
    row: dict[str, Any], bytes_limit: int | None, cap: int, tries: int
) -> list[int]:
    """Batch sizes to try, largest first, for the biggest phase-1 batch that fits.

    The first is what the B=3 row's memory predicts: the device peak (or, without one, the
    compiled step's temporaries) grows linearly with B above the fixed state, and 90% of
    `bytes_limit` may be used. Each next try is 3/4 of the one before. Without `bytes_limit`
    (CPU) the first is `cap`. Every candidate is above the row's own batch and at most `cap`.
    """
    base = int(row["B"])
    mem = row["memory"]
    fixed = mem.get("argument_bytes", 0) + mem.get("output_bytes", 0)
    used = mem.get("peak_bytes_in_use", mem.get("temp_bytes", 0) + fixed)
    per_sample = max(used - fixed, 1) / base
    first = cap if bytes_limit is None else int((0.9 * bytes_limit - fixed) // per_sample)
    out: list[int] = []
    b = min(first, cap)
    while b > base and len(out) < tries:
        out.append(b)
        b = int(b * 0.75)
    return out


def targets(summary: dict[str, Any]) -> dict[str, Any]:
    """The issue's targets against the bench rows: phase-1 step <= 50 ms in float32 at B=3 and
    within 24 GiB; phase 2 (nm) >= 100 steps/s. None where the row (or the device peak) is
    missing."""
    rows = {r["label"]: r for r in summary.get("bench", {}).get("rows", [])}
    out: dict[str, Any] = {}
    f32 = rows.get("skel_f32")
    step_s = None if f32 is None else f32["compute_s_per_step"]
    out["skel_f32_step_s"] = step_s
    out["skel_f32_step_le_50ms"] = None if step_s is None else step_s <= 0.05
    peak = None if f32 is None else f32["memory"].get("peak_bytes_in_use")
    out["skel_f32_peak_gib"] = None if peak is None else peak / GIB
    out["skel_f32_peak_le_24gib"] = None if peak is None else peak <= RTX_3090_BYTES
    # Only a GPU allocator can be capped; on the CPU the row runs uncapped and proves nothing.
    capped = summary.get("stages", {}).get("bench_skel_f32_24gib", {}).get("status")
    meaningful = summary.get("capped_24gib", {}).get("meaningful", False)
    ran = meaningful and capped is not None and not capped.startswith("skipped")
    out["skel_f32_runs_capped_at_24gib"] = (capped == "ok") if ran else None
    nm = rows.get("dyn_nm")
    out["dyn_nm_steps_per_s"] = None if nm is None else nm["steps_per_s"]
    out["dyn_nm_ge_100_steps_per_s"] = None if nm is None else nm["steps_per_s"] >= 100
    return out


def commit_of(repo: Path) -> tuple[str | None, bool | None]:
    """(commit hash, whether tracked files differ from it): $NMJAX_COMMIT when set (a copy of the
    tree without .git), else git; (None, None) when neither knows."""
    given = os.environ.get("NMJAX_COMMIT")
    if given:
        return given, None
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True, check=True
        ).stdout.strip()
        status = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=repo,
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return None, None
    return head, bool(status.strip())


# --- running stages ------------------------------------------------------------------------------


class Runner:
    """Runs the stages of `plan` in child processes and keeps `summary` (and summary.json)
    up to date after each."""

    def __init__(self, plan: Plan, args: argparse.Namespace):
        self.plan, self.args = plan, args
        self.out, self.work = Path(args.out), Path(args.work)
        self.python = sys.executable
        self.deadline = args.started_at + (args.budget or plan.budget_s)
        self.work.mkdir(parents=True, exist_ok=True)
        # A fresh compilation cache per script run: stages that compile the same program (the
        # 24 GiB row repeats the float32 one) load it instead, and no timing of this run comes
        # from an earlier run's cache.
        cache = self.work / "jax_cache"
        # Nor may a run or curves of an earlier script run be evaluated or packed as this one's.
        for stale in (cache, self.work / "run", self.work / "curves"):
            shutil.rmtree(stale, ignore_errors=True)
        self.env = {
            **os.environ,
            **plan.env,
            "NMJAX_DATA": str(self.work / "data"),
            "JAX_COMPILATION_CACHE_DIR": str(cache),
            "PYTHONUNBUFFERED": "1",
        }
        self.child: subprocess.Popen | None = None
        commit, dirty = commit_of(REPO)
        self.summary: dict[str, Any] = {
            "mode": "dry-run" if args.dry_run else "gpu",
            "commit": commit,
            "commit_dirty": dirty,
            "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(args.started_at)),
            "budget_s": args.budget or plan.budget_s,
            "install": {
                "status": args.install_status,
                "seconds": args.install_seconds,
                "jax_version": args.jax_version,
                "command": args.install_command,
                "python": self.python,
            },
            "plan": {
                "preset": plan.preset,
                "data": DATA,
                "keypoints": plan.keypoints,
                "skel_steps": plan.skel_steps,
                "dyn_steps": plan.dyn_steps,
                "mem_fraction": plan.env.get("XLA_PYTHON_CLIENT_MEM_FRACTION"),
                "train_seconds_target": plan.train_seconds,
            },
            "stages": {},
            "bench": {"environment": None, "rows": []},
        }

    # -- bookkeeping

    def save(self) -> None:
        self.summary["elapsed_s"] = round(time.time() - self.args.started_at, 1)
        self.summary["targets"] = targets(self.summary)
        write_json_atomic(self.out / "summary.json", self.summary)

    def record(self, name: str, **info: Any) -> None:
        """Stage `name`'s entry (replacing an earlier try's) and a rewritten summary.json."""
        self.summary["stages"][name] = info
        self.save()

    # -- child processes

    def run(self, name: str, argv: list[str], limit: float, env: dict[str, str] | None = None):
        """Runs `argv` for at most `limit` seconds; returns (status, seconds, last lines)."""
        print(f"\n=== {name} (limit {limit:.0f} s): {shlex.join(argv)}", flush=True)
        tail: collections.deque[str] = collections.deque(maxlen=25)
        tic = time.time()
        self.child = subprocess.Popen(
            argv,
            cwd=REPO,
            env=env or self.env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            errors="replace",
            start_new_session=True,  # its own process group: a timeout ends its children too
        )
        reader = threading.Thread(target=_echo, args=(self.child.stdout, tail), daemon=True)
        reader.start()
        try:
            rc = self.child.wait(timeout=max(limit, 1.0))
            status = "ok" if rc == 0 else f"failed (exit {rc})"
        except subprocess.TimeoutExpired:
            self.kill_child()
            status = "timeout"
        except BaseException:  # SIGTERM of the whole script (raised as KeyboardInterrupt)
            self.kill_child()
            seconds = round(time.time() - tic, 1)
            self.summary["stages"][name] = {"status": "interrupted", "seconds": seconds}
            raise
        finally:
            reader.join(timeout=5)
            self.child.stdout.close()
            self.child = None
        seconds = round(time.time() - tic, 1)
        print(f"=== {name}: {status} after {seconds} s", flush=True)
        return status, seconds, list(tail)

    def kill_child(self) -> None:
        child = self.child
        if child is None or child.poll() is not None:
            return
        for sig, wait in ((signal.SIGTERM, 10), (signal.SIGKILL, 5)):
            try:
                os.killpg(child.pid, sig)
            except ProcessLookupError:
                return
            try:
                child.wait(timeout=wait)
                return
            except subprocess.TimeoutExpired:
                continue

    def stage(self, name: str, argv: list[str], env: dict[str, str] | None = None) -> bool:
        """Runs one stage under its limit unless it no longer fits; records it; True if ok."""
        limit = stage_limit(self.plan, name, time.time(), self.deadline)
        if limit < self.plan.minimum[name]:
            self.record(name, status="skipped (out of time)", limit_s=round(limit, 1))
            return False
        status, seconds, tail = self.run(name, argv, limit, env)
        info: dict[str, Any] = {"status": status, "seconds": seconds, "limit_s": round(limit, 1)}
        info["command"] = shlex.join(argv)
        if status != "ok":
            info["output_tail"] = tail
        self.record(name, **info)
        return status == "ok"

    def nmjax(self, *args: str) -> list[str]:
        return [self.python, "-m", "nmjax.cli", *args]

    # -- the stages

    def devices(self) -> None:
        path = self.work / "devices.json"
        if self.stage("devices", [self.python, "-c", DEVICES_CODE, str(path)]):
            self.summary["devices"] = json.loads(path.read_text())
            self.save()

    def data(self) -> None:
        root = self.work / "data" / DATA
        self.stage(
            "data",
            self.nmjax("prepare-data", "--data", DATA, "--root", str(root), *self.plan.data_args),
        )

    def bench(self, label: str, name: str, argv: list[str], env: dict[str, str] | None = None):
        """One `nmjax bench` row measured in its own process; appended to summary["bench"]."""
        path = self.work / "bench" / f"{label}.json"
        path.unlink(missing_ok=True)
        cmd = self.nmjax("bench", "--data", DATA, "--same-process", "--out", str(path), *argv)
        ok = self.stage(name, cmd, env)
        if ok:
            result = json.loads(path.read_text())
            bench = self.summary["bench"]
            bench["environment"] = bench["environment"] or result["environment"]
            bench["rows"].append({"label": label, **result["rows"][0]})
            self.save()
        return ok

    def skel_row_args(self, dtype: str, batch: int | None = None) -> list[str]:
        timed, warmup = self.plan.skel_steps
        argv = ["--phase", "skel", "--preset", self.plan.preset, "--compute-dtype", dtype]
        argv += ["--steps", str(timed), "--warmup", str(warmup)]
        overrides = [f"skel:model.num_keypoints={self.plan.keypoints}", *self.plan.skel_overrides]
        if batch is not None:
            overrides.append(f"skel:data.batch_size={batch}")
        for item in overrides:
            argv += ["--set", item]
        return argv

    def dyn_row_args(self, model: str) -> list[str]:
        timed, warmup = self.plan.dyn_steps
        argv = ["--phase", "dyn", "--preset", self.plan.preset, "--dyn-model", model]
        return argv + [
            "--keypoints",
            str(self.plan.keypoints),
            "--steps",
            str(timed),
            "--warmup",
            str(warmup),
        ]

    def row(self, label: str) -> dict[str, Any] | None:
        return next((r for r in self.summary["bench"]["rows"] if r["label"] == label), None)

    def max_batch(self) -> None:
        name = "bench_skel_max_batch"
        f32 = self.row("skel_f32")
        if f32 is None:
            self.record(name, status="skipped (no float32 B=3 row to estimate from)")
            return
        limit_bytes = (self.summary.get("devices") or {}).get("bytes_limit")
        tries = max_batch_candidates(
            f32, limit_bytes, self.plan.max_batch_cap, self.plan.max_batch_tries
        )
        self.summary["max_batch"] = {"candidates": tries, "bytes_limit": limit_bytes, "tried": []}
        if not tries:
            self.record(name, status=f"skipped (B={f32['B']} is all the device's memory predicts)")
        for batch in tries:
            ok = self.bench("skel_f32_max_batch", name, self.skel_row_args("float32", batch))
            status = self.summary["stages"][name]["status"]
            self.summary["max_batch"]["tried"].append({"B": batch, "status": status})
            if ok:
                self.summary["max_batch"]["largest_fitting"] = batch
                break
            if status.startswith("skipped"):
                break
        self.save()

    def capped_24gib(self) -> None:
        name = "bench_skel_f32_24gib"
        limit_bytes = (self.summary.get("devices") or {}).get("bytes_limit")
        if not limit_bytes and not self.args.dry_run:
            self.record(name, status="skipped (the device reported no bytes_limit to cap)")
            return
        env = dict(self.env)
        if limit_bytes:
            # bytes_limit is MEM_FRACTION of the device; the cap is the same share of 24 GiB.
            fraction = RTX_3090_BYTES / (limit_bytes / MEM_FRACTION)
            env["XLA_PYTHON_CLIENT_MEM_FRACTION"] = f"{min(fraction, MEM_FRACTION):.4f}"
        self.summary["capped_24gib"] = {
            "mem_fraction": env.get("XLA_PYTHON_CLIENT_MEM_FRACTION"),
            "meaningful": bool(limit_bytes),
        }
        self.bench("skel_f32_24gib", name, self.skel_row_args("float32"), env)

    def train(self) -> None:
        run = self.work / "run"
        seconds = train_seconds(self.plan, time.time(), self.deadline)
        if seconds is None:
            self.record("train", status="skipped (out of time)")
            return
        argv = self.nmjax(
            "train-skel",
            *("--data", DATA, "--preset", self.plan.preset, "--run", str(run), "--overwrite"),
            *("--no-progress", "--set", f"time_limit_minutes={seconds / 60:.4f}"),
            *self.plan.train_args,
        )
        limit = seconds + self.plan.train_overhead_s
        status, wall, tail = self.run("train", argv, limit)
        info: dict[str, Any] = {"status": status, "seconds": wall, "limit_s": round(limit, 1)}
        info["command"] = shlex.join(argv)
        if status != "ok":
            info["output_tail"] = tail
        self.record("train", **info)
        if (run / "metrics.jsonl").is_file():
            self.summary["train"] = run_summary(run, seconds, wall)
            self.save()

    def evaluate(self) -> None:
        run = self.work / "run"
        if not (run / "checkpoints").is_dir():
            self.record("evaluate", status="skipped (no trained run)")
            return
        out = run / "eval"
        if self.stage(
            "evaluate",
            self.nmjax("evaluate", "--run", str(run), "--out", str(out), *self.plan.eval_args),
        ):
            self.summary["evaluate"] = json.loads((out / "results.json").read_text())
            self.save()

    def curves(self) -> None:
        run, out = self.work / "run", self.work / "curves"
        if not (run / "metrics.jsonl").is_file():
            self.record("curves", status="skipped (no trained run)")
            return
        train_cmd = self.summary["stages"].get("train", {}).get("command", "")
        wall = self.summary["stages"].get("train", {}).get("seconds")
        argv = [self.python, str(REPO / "experiments" / "train_skel_curves.py"), "--run", str(run)]
        argv += ["--out", str(out), "--command", train_cmd]
        if wall is not None:
            argv += ["--wall-minutes", f"{wall / 60:.2f}"]
        if self.stage("curves", argv):
            result = json.loads((out / f"train_skel_{DATA}.json").read_text())
            self.summary["curves"] = {
                "steps": result["steps"],
                "final_val": result["final_val"],
                "train": result["train"],
                "val": result["val"],
            }
            shutil.copyfile(out / f"train_skel_{DATA}.png", self.out / "curves.png")
            self.save()

    def pack(self) -> None:
        run = self.work / "run"
        if not run.is_dir():
            self.record("pack", status="skipped (no run folder)")
            return
        tic = time.time()
        members = pack_run(run, self.work / "curves", self.out / "run.tar.gz")
        self.summary["artefacts"] = {"archive": "run.tar.gz", "members": members}
        self.record("pack", status="ok", seconds=round(time.time() - tic, 1))

    def all(self) -> None:
        self.save()
        if not runnable(self.args.install_status):
            for name in STAGES:
                self.record(name, status=f"skipped (install {self.args.install_status})")
            return
        stages = {
            "devices": self.devices,
            "data": self.data,
            "bench_skel_f32": lambda: self.bench(
                "skel_f32", "bench_skel_f32", self.skel_row_args("float32")
            ),
            "bench_skel_f32_24gib": self.capped_24gib,
            "bench_dyn_nm": lambda: self.bench("dyn_nm", "bench_dyn_nm", self.dyn_row_args("nm")),
            "bench_dyn_vrnn": lambda: self.bench(
                "dyn_vrnn", "bench_dyn_vrnn", self.dyn_row_args("vrnn")
            ),
            "bench_skel_bf16": lambda: self.bench(
                "skel_bf16", "bench_skel_bf16", self.skel_row_args("bfloat16")
            ),
            "train": self.train,
            "evaluate": self.evaluate,
            "curves": self.curves,
            "pack": self.pack,
            "bench_skel_max_batch": self.max_batch,
        }
        assert tuple(stages) == STAGES  # one order, documented in STAGES
        for name, run_stage in stages.items():
            if name in self.args.skip:
                self.record(name, status="skipped (--skip)")
            else:
                run_stage()


def runnable(install_status: str) -> bool:
    """Whether the stages can run after the install stage ended with `install_status`: the
    pinned install, the machine's own jax ("image ...") or a dry run."""
    return install_status in ("ok", "dry-run") or install_status.startswith("image")


def _echo(stream: Any, tail: collections.deque[str]) -> None:
    """Copies a child's output to ours line by line, keeping the last lines."""
    for line in stream:
        sys.stdout.write(line)
        sys.stdout.flush()
        tail.append(line.rstrip("\n"))


def run_summary(run: Path, time_limit_s: float, wall_s: float) -> dict[str, Any]:
    """What the training run did, from its config.json and metrics.jsonl."""
    config = json.loads((run / "config.json").read_text())
    records = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines() if x.strip()]
    train = [r for r in records if "train/loss" in r]
    val = [r for r in records if "val/loss" in r]
    rates = [r["train/steps_per_s"] for r in train if "train/steps_per_s" in r]
    data, model = config["data"], config["model"]
    last_step = train[-1]["step"] if train else 0
    return {
        "time_limit_s": time_limit_s,
        "wall_s": wall_s,
        "steps": last_step,
        "configured_steps": config["loop"]["steps"],
        "stopped_by_budget": last_step < config["loop"]["steps"],
        # the first interval includes compilation; the later ones are the training rate
        "steps_per_s_after_first_log": rates[1:],
        "shape": {
            "G": model["grid"],
            "C": model["channels"],
            "K": model["num_keypoints"],
            "B": data["batch_size"],
            "T": data["frames"],
            "compute_dtype": model["compute_dtype"],
        },
        "final_train": train[-1] if train else None,
        "final_val": val[-1] if val else None,
    }


def pack_run(run: Path, curves: Path, archive: Path) -> list[str]:
    """Writes `archive` (tar.gz, atomically) with the run's ARTEFACTS that exist and the curves
    folder; returns the member names. Checkpoints never go in."""
    archive.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{archive.name}.", suffix=".tmp", dir=archive.parent)
    os.close(fd)
    try:
        with tarfile.open(tmp, "w:gz") as tar:
            for name in ARTEFACTS:
                if (run / name).exists():
                    tar.add(run / name, arcname=f"run/{name}")
            if curves.is_dir():
                tar.add(curves, arcname="curves")
            members = tar.getnames()
        os.chmod(tmp, 0o644)  # mkstemp makes it private
        os.replace(tmp, archive)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return members


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dry-run", action="store_true", help="CPU, tiny preset, no install")
    parser.add_argument("--out", default="gpu_out", help="results folder (what comes back)")
    parser.add_argument("--work", default=None, help="run folder, data, bench rows (default: WORK)")
    parser.add_argument("--budget", type=float, default=None, help="seconds for everything")
    parser.add_argument(
        "--started-at", type=float, default=None, help="epoch seconds the script began"
    )
    parser.add_argument(
        "--skip", nargs="+", default=[], choices=STAGES, metavar="STAGE", help="stages to leave out"
    )
    parser.add_argument(
        "--train-seconds",
        type=float,
        default=None,
        help="target wall budget of the training loop (default 240 on the GPU)",
    )
    parser.add_argument("--install-status", default="not run")
    parser.add_argument("--install-seconds", type=float, default=None)
    parser.add_argument("--install-command", default=None)
    parser.add_argument("--jax-version", default=None)
    args = parser.parse_args(argv)
    for name in ("budget", "train_seconds"):
        value = getattr(args, name)
        if value is not None and value <= 0:
            parser.error(f"--{name.replace('_', '-')} must be positive seconds, got {value}")
    if args.started_at is None:
        args.started_at = time.time()
    if args.work is None:
        args.work = str(REPO / "runs" / ("gpu-dry-run" if args.dry_run else "gpu-paper-scale"))
    return args


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    plan = DRY if args.dry_run else GPU
    if args.train_seconds is not None:
        plan = dataclasses.replace(plan, train_seconds=args.train_seconds)
    runner = Runner(plan, args)

    def terminate(signum: int, _frame: Any) -> None:
        raise KeyboardInterrupt(f"signal {signum}")

    signal.signal(signal.SIGTERM, terminate)
    try:
        runner.all()
    except KeyboardInterrupt as err:
        runner.kill_child()
        runner.summary["interrupted"] = str(err) or "interrupted"
    finally:
        runner.save()
    stages = runner.summary["stages"]
    failed = [n for n, s in stages.items() if not s["status"].startswith(("ok", "skipped"))]
    print(f"\nsummary: {runner.out / 'summary.json'}; failed stages: {failed or 'none'}")
    print(json.dumps(runner.summary["targets"], indent=1))
    bad = failed or "interrupted" in runner.summary or not runnable(args.install_status)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
