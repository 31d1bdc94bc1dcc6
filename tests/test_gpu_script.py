"""The paper-scale GPU script (experiments/gpu/paper_scale.sh and .py): its dry run end to end on
the CPU, so that it cannot rot between the rare GPU loans, and its planning helpers."""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
import tarfile
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest
from experiment_scripts import load_experiment

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "experiments" / "gpu" / "paper_scale.sh"
# What the device machine returns from OUT: at most 8 files, plain names.
RETURNABLE = re.compile(r"[A-Za-z0-9._-]+")


paper_scale = load_experiment("gpu/paper_scale.py")


def _pinned_jax() -> str:
    deps = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    return next(d.split("==")[1] for d in deps if d.startswith("jax=="))


@pytest.fixture(scope="module")
def dry_run(tmp_path_factory):
    """(completed process, OUT, WORK) of one dry run; no time limit: CI machines are slow."""
    tmp = tmp_path_factory.mktemp("gpu")
    out, work = tmp / "out", tmp / "work"
    env = {**os.environ, "PYTHON": sys.executable}
    env.pop("NMJAX_COMMIT", None)
    done = subprocess.run(
        ["bash", str(SCRIPT), "--dry-run", "--out", str(out), "--work", str(work)],
        cwd=tmp,  # the script finds the repository itself
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    return done, out, work


def test_dry_run_summary_has_every_stage_and_real_results(dry_run):
    done, out, work = dry_run
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["mode"] == "dry-run"
    # The install stage is only described, with the pin read from pyproject.toml.
    pin = _pinned_jax()
    assert summary["install"]["status"] == "dry-run"
    assert summary["install"]["jax_version"] == pin
    assert f"'jax[cuda12]=={pin}' -e ." in summary["install"]["command"]
    head = subprocess.run(
        ["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True, check=True
    ).stdout.strip()
    assert summary["commit"] == head

    stages = summary["stages"]
    assert set(stages) == set(paper_scale.STAGES)
    assert {name: s["status"] for name, s in stages.items()} == dict.fromkeys(stages, "ok")
    assert summary["devices"]["backend"] == "cpu" and summary["devices"]["device_count"] >= 1
    assert summary["devices"]["provenance"]["commit"] == head  # nmjax.provenance's stamp

    rows = {r["label"]: r for r in summary["bench"]["rows"]}
    assert set(rows) == {
        "skel_f32",
        "skel_bf16",
        "dyn_nm",
        "dyn_vrnn",
        "skel_f32_max_batch",
        "skel_f32_24gib",
    }
    for label, row in rows.items():
        assert math.isfinite(row["steps_per_s"]) and row["steps_per_s"] > 0, label
        assert math.isfinite(row["frames_per_s"]) and row["compile_s"] > 0, label
        assert row["memory"]["temp_bytes"] > 0, label
    assert rows["skel_f32"]["compute_dtype"] == "float32" and rows["skel_f32"]["K"] == 6
    assert rows["skel_bf16"]["compute_dtype"] == "bfloat16"
    assert (rows["dyn_nm"]["model"], rows["dyn_vrnn"]["model"]) == ("nm", "vrnn")
    assert rows["skel_f32_max_batch"]["B"] == summary["max_batch"]["largest_fitting"]
    assert rows["skel_f32_max_batch"]["B"] > rows["skel_f32"]["B"]
    assert summary["bench"]["environment"]["backend"] == "cpu"

    train = summary["train"]
    assert train["steps"] == 4 and train["shape"]["G"] == 8
    assert math.isfinite(train["final_val"]["val/loss"])
    phase1 = summary["evaluate"]["phase1"]
    for key in ("sc", "sc_fixed_nodes"):
        assert 0.0 < phase1[key]["score"] <= 1.0, key
    assert math.isfinite(phase1["tracking"]["mean"])
    assert math.isfinite(phase1["bone_length_variation"]["mean"])
    # The skeleton against synth-arm's true tree, on the nodes the run's skeleton.json keeps.
    assert math.isfinite(phase1["joint_distance"]["mean"])
    for key in ("joint_coverage_0.10", "bone_recall"):
        assert 0.0 <= phase1[key] <= 1.0, key
    edges = phase1["edge_precision_within_2_hops"]  # nan only for a skeleton of one kept node
    assert 0.0 <= edges <= 1.0 or (math.isnan(edges) and phase1["skeleton_kept_nodes"] == 1)
    assert 1 <= phase1["distinct_nodes"] <= phase1["skeleton_kept_nodes"]
    assert summary["curves"]["steps"] == 4 and "loss" in summary["curves"]["train"]

    targets = summary["targets"]
    assert targets["skel_f32_step_s"] == rows["skel_f32"]["compute_s_per_step"]
    assert targets["dyn_nm_steps_per_s"] == rows["dyn_nm"]["steps_per_s"]
    # No device peak and no allocator cap on the CPU: those targets stay open.
    assert targets["skel_f32_peak_le_24gib"] is None
    assert targets["skel_f32_runs_capped_at_24gib"] is None


def test_dry_run_out_holds_the_artefacts_and_no_checkpoints(dry_run):
    done, out, work = dry_run
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]
    files = sorted(p.name for p in out.iterdir())
    assert files == ["curves.png", "paper_scale.log", "run.tar.gz", "summary.json"]
    assert all(RETURNABLE.fullmatch(name) for name in files)
    assert "=== train: ok" in (out / "paper_scale.log").read_text()
    run = work / "run"
    assert (run / "checkpoints").is_dir()  # they exist, but stay behind
    with tarfile.open(out / "run.tar.gz") as tar:
        names = tar.getnames()
        assert not [n for n in names if "checkpoints" in n or n.startswith("run/tb")]
        for name in ("skeleton.json", "keypoints_train.npz", "keypoints_test.npz", "config.json"):
            assert f"run/{name}" in names, name
        assert any(re.fullmatch(r"run/figures/keypoints_\d+\.png", n) for n in names)
        assert "run/eval/results.json" in names and "curves/train_skel_synth-arm.png" in names
        skeleton = json.load(tar.extractfile("run/skeleton.json"))
        assert skeleton == json.loads((run / "skeleton.json").read_text())
        with np.load(tar.extractfile("run/keypoints_test.npz")) as kp:
            assert kp.files and kp[kp.files[0]].shape[1:] == (6, 4)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["artefacts"]["members"] == names


def test_dry_run_refuses_a_missing_pin(tmp_path):
    # A copy of the script beside a pyproject.toml without the jax pin must stop, naming it.
    root = tmp_path / "repo"
    (root / "experiments" / "gpu").mkdir(parents=True)
    (root / "experiments" / "gpu" / "paper_scale.sh").write_text(SCRIPT.read_text())
    (root / "pyproject.toml").write_text('[project]\ndependencies = ["numpy==2.4.6"]\n')
    done = subprocess.run(
        ["bash", str(root / "experiments" / "gpu" / "paper_scale.sh"), "--dry-run"],
        cwd=tmp_path,
        env={**os.environ, "OUT": str(tmp_path / "out")},
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 2
    assert "cannot read the jax pin" in done.stdout and "pyproject.toml" in done.stdout
    assert not (tmp_path / "out" / "summary.json").exists()


def test_without_a_registry_the_machines_own_jax_runs_the_stages(tmp_path):
    """A pin no registry serves stands in for a machine that reaches none: the script falls back
    to python3's own jax with src/ on the path (here every stage skipped, so nothing heavy runs)."""
    root = tmp_path / "repo"
    (root / "experiments" / "gpu").mkdir(parents=True)
    for name in ("paper_scale.sh", "paper_scale.py"):
        (root / "experiments" / "gpu" / name).write_text((SCRIPT.parent / name).read_text())
    (root / "pyproject.toml").write_text('[project]\ndependencies = [\n    "jax==0.0.0.999",\n]\n')
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    wrapper = bin_dir / "python3"  # the "machine's" python3, which has jax
    wrapper.write_text(f'#!/bin/sh\nexec "{sys.executable}" "$@"\n')
    wrapper.chmod(0o755)
    out = tmp_path / "out"
    done = subprocess.run(
        [
            "bash",
            str(root / "experiments" / "gpu" / "paper_scale.sh"),
            "--out",
            str(out),
            "--work",
            str(tmp_path / "work"),
            "--skip",
            *paper_scale.STAGES,
        ],
        cwd=tmp_path,
        env={
            **{k: v for k, v in os.environ.items() if k != "NMJAX_COMMIT"},
            "PATH": f"{bin_dir}:{os.environ['PATH']}",
        },
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    assert "no package registry answers" in done.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert summary["install"]["status"].startswith("image")
    assert summary["install"]["python"] == sys.executable
    assert {s["status"] for s in summary["stages"].values()} == {"skipped (--skip)"}
    assert summary["commit"] is None  # the copy has no .git and NMJAX_COMMIT is unset


def test_stage_limits_keep_time_for_the_reserved_stages():
    plan = paper_scale.GPU
    reserve = sum(plan.minimum[s] for s in paper_scale.RESERVED)
    # Plenty of time: the stage's own limit.
    assert (
        paper_scale.stage_limit(plan, "bench_skel_f32", 0.0, 1e6) == plan.limits["bench_skel_f32"]
    )
    # Little time: what is left once evaluate, curves and pack are kept free.
    assert paper_scale.stage_limit(plan, "bench_skel_f32", 0.0, 100.0 + reserve) == 100.0
    # After pack nothing is reserved any more.
    assert paper_scale.stage_limit(plan, "bench_skel_max_batch", 0.0, 100.0) == 100.0
    assert paper_scale.train_seconds(plan, 0.0, 1e6) == plan.train_seconds
    left = 130.0
    deadline = left + reserve + plan.train_overhead_s
    assert paper_scale.train_seconds(plan, 0.0, deadline) == pytest.approx(left)
    assert paper_scale.train_seconds(plan, 0.0, deadline - left + 10.0) is None


def test_max_batch_candidates_scale_the_measured_peak():
    gib = 2**30
    row = {
        "B": 3,
        "memory": {"argument_bytes": gib, "output_bytes": gib, "peak_bytes_in_use": 20 * gib},
    }
    # 6 GiB per sample above 2 GiB of state; 90% of 100 GiB usable -> 14.
    assert paper_scale.max_batch_candidates(row, 100 * gib, cap=64, tries=3) == [14, 10, 7]
    assert paper_scale.max_batch_candidates(row, 100 * gib, cap=12, tries=2) == [12, 9]
    assert paper_scale.max_batch_candidates(row, 10 * gib, cap=64, tries=3) == []  # B=3 is all
    # No device limit (CPU): the cap, from the compiled step's temporaries.
    cpu = {"B": 2, "memory": {"argument_bytes": 10, "output_bytes": 10, "temp_bytes": 100}}
    assert paper_scale.max_batch_candidates(cpu, None, cap=4, tries=1) == [4]


def test_targets_read_the_rows():
    gib = 2**30
    summary = {
        "bench": {
            "rows": [
                {
                    "label": "skel_f32",
                    "compute_s_per_step": 0.04,
                    "memory": {"peak_bytes_in_use": 20 * gib},
                },
                {"label": "dyn_nm", "steps_per_s": 90.0},
            ]
        },
        "stages": {"bench_skel_f32_24gib": {"status": "failed (exit 1)"}},
        "capped_24gib": {"meaningful": True},
    }
    t = paper_scale.targets(summary)
    assert t["skel_f32_step_le_50ms"] is True and t["skel_f32_peak_gib"] == 20.0
    assert t["skel_f32_peak_le_24gib"] is True and t["skel_f32_runs_capped_at_24gib"] is False
    assert t["dyn_nm_ge_100_steps_per_s"] is False
    empty = paper_scale.targets({})
    assert set(empty.values()) == {None}


def _gone(pid: int) -> bool:
    """The process has exited (absent, or a zombie waiting for init)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return True
    return stat.rsplit(")", 1)[1].split()[0] == "Z"


def test_a_stage_past_its_limit_is_killed_with_its_children_and_a_failure_recorded(tmp_path):
    args = paper_scale.parse_args(
        ["--dry-run", "--out", str(tmp_path / "out"), "--work", str(tmp_path / "work")]
    )
    runner = paper_scale.Runner(paper_scale.DRY, args)
    marker = tmp_path / "grandchild.pid"
    code = (
        "import subprocess, sys, time\n"
        "p = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(120)'])\n"
        f"open({str(marker)!r}, 'w').write(str(p.pid))\n"
        "print('started', flush=True)\n"
        "time.sleep(120)\n"
    )
    status, seconds, tail = runner.run("sleeper", [sys.executable, "-c", code], limit=5)
    assert status == "timeout" and seconds < 60 and tail == ["started"]
    grandchild = int(marker.read_text())
    deadline = time.time() + 10
    while not _gone(grandchild) and time.time() < deadline:
        time.sleep(0.1)
    assert _gone(grandchild)

    failing = [sys.executable, "-c", "print('boom'); raise SystemExit(3)"]
    assert runner.stage("devices", failing) is False
    entry = json.loads((tmp_path / "out" / "summary.json").read_text())["stages"]["devices"]
    assert entry["status"] == "failed (exit 3)" and entry["output_tail"] == ["boom"]
