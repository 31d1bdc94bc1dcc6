"""The faults the one training loop must survive, in both phases (issue 16).

- a process killed mid-step or mid-checkpoint-save (a torn newest checkpoint and a metrics line
  past the last checkpoint) resumes from the last complete step, config.json and the metrics log
  intact;
- `--resume` honours --steps and the cadence, and refuses --set / --seed / --batch-size changes
  and a missing checkpoint before anything in the run folder is written;
- a NaN loss stops phase 2 too, with the step, keeping the last good checkpoint.
"""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import pytest
from tiny_configs import fake_run_dyn_config as tiny_cfg
from tiny_configs import short_skel_config as skel_cfg
from tiny_runs import poison_after

from nmjax import atomic, run_folder
from nmjax.cli import main as nmjax_main
from nmjax.config import resolve_epochs
from nmjax.config_io import replace_fields
from nmjax.train import dyn, loop, metric_log, skel, trained

TORN = "3.orbax-checkpoint-tmp-1764633600"  # what orbax leaves of a save killed before its rename


def _folder(run) -> dict[str, bytes]:
    return {str(p.relative_to(run)): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}


def _kill_mid_step(run) -> None:
    """The state of `run` after a process died while saving step 3, having logged step 3."""
    (run / run_folder.CHECKPOINTS / TORN / "state").mkdir(parents=True)
    (run / run_folder.CHECKPOINTS / TORN / "state" / "partial").write_bytes(b"half written")
    with open(run / run_folder.METRICS_FILE, "a") as f:
        f.write(json.dumps({"step": 3, "train/loss": 1e9}) + "\n")


def _train_steps(run) -> list[int]:
    return [r["step"] for r in metric_log.read_metrics(run) if "train/loss" in r]


def _refused(argv, capsys, run, named: str) -> None:
    before = _folder(run)
    assert nmjax_main(argv) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert named in line
    assert _folder(run) == before  # nothing written, config.json included


def test_phase1_resume_rules_and_torn_checkpoint(data_root, tmp_path, capsys):
    cfg = skel_cfg(data_root, steps=2, val_every=2)
    run = tmp_path / "run"
    skel.train_skeleton(replace_fields(cfg, run=str(run)), progress=False, finalize=False)
    argv = ["train-skel", "--run", str(run), "--resume", "--steps", "4", "--no-progress"]
    for change, named in (
        ("model.channels=8", "model.channels"),
        ("seed=3", "seed"),
        ("data.batch_size=2", "data.batch_size"),
        ("weights.vol=2.0", "weights.vol"),
    ):
        _refused([*argv, "--set", change], capsys, run, named)
    _refused([*argv, "--data", "synth-hand"], capsys, run, "synth-arm")
    empty = tmp_path / "empty"
    # A folder as the trainer makes it before its first checkpoint: the epochs resolved (the
    # two-sequence set has 1 training sequence, 1 step an epoch at B = 1).
    run_folder.prepare_run_dir(empty, resume=False, config=resolve_epochs(cfg, 1, 1))
    no_checkpoint = "no complete checkpoint"
    _refused(["train-skel", "--run", str(empty), "--resume"], capsys, empty, no_checkpoint)

    _kill_mid_step(run)
    config_before = json.loads((run / run_folder.CONFIG_FILE).read_text())
    # --steps and the log cadence may change on a resume.
    resumed = replace_fields(cfg, steps=4, log_every=2)
    summary = skel.train_skeleton(
        replace_fields(resumed, run=str(run)), resume=True, progress=False, finalize=False
    )
    assert summary.start_step == 2 and summary.step == 4
    assert _train_steps(run) == [1, 2, 4]  # the dead process's step 3 is gone, 4 logged anew
    config = json.loads((run / run_folder.CONFIG_FILE).read_text())
    changed = {**config_before["loop"], "steps": 4, "log_every": 2}
    assert config == {**config_before, "loop": changed}
    assert 4 in run_folder.checkpoint_steps(run)


def test_phase2_resume_rules_torn_checkpoint_and_nan_stop(fake_run, tmp_path, capsys):
    run = tmp_path / "dyn"
    cfg = tiny_cfg(fake_run, run, steps=2, log_every=1, val_every=2, ckpt_every=1)
    dyn.train_dynamics(cfg, progress=False)
    argv = ["train-dyn", "--run", str(run), "--resume", "--steps", "4", "--no-progress"]
    _refused([*argv, "--seed", str(cfg.seed + 1)], capsys, run, "seed")
    _refused([*argv, "--batch-size", str(2 * cfg.data.batch_size)], capsys, run, "data.batch_size")
    _refused([*argv, "--set", "model.hidden=8"], capsys, run, "model.hidden")
    _refused([*argv, "--model", "vrnn"], capsys, run, "model.model")
    empty = tmp_path / "empty"
    saved = run_folder.load_config(run, type(cfg))  # as the trainer resolved it
    run_folder.prepare_run_dir(
        empty, resume=False, config=dataclasses.replace(saved, run=str(empty))
    )
    no_checkpoint = "no complete checkpoint"
    _refused(["train-dyn", "--run", str(empty), "--resume"], capsys, empty, no_checkpoint)

    _kill_mid_step(run)
    config_before = json.loads((run / run_folder.CONFIG_FILE).read_text())
    assert nmjax_main([*argv, "--set", "val_every=4"]) == 0
    assert _train_steps(run) == [1, 2, 3, 4]
    config = json.loads((run / run_folder.CONFIG_FILE).read_text())
    changed = {**config_before["loop"], "steps": 4, "val_every": 4}
    assert config == {**config_before, "loop": changed}

    nan_run = tmp_path / "nan"
    bad = replace_fields(cfg, run=str(nan_run), steps=3)
    with pytest.raises(loop.NonFiniteLossError, match="at step 2"):
        dyn.train_dynamics(bad, progress=False, step_hook=poison_after(1))
    assert run_folder.checkpoint_steps(nan_run) == [1]
    restored = trained.restore_dynamics(nan_run)
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves(restored))


def test_missing_export_is_an_error_naming_the_command(tmp_path, capsys, fake_run):
    phase1 = tmp_path / "skel-synth-arm-1"
    phase1.mkdir()
    atomic.write_json(
        phase1 / "skeleton.json", json.loads((fake_run / "skeleton.json").read_text())
    )
    argv = ["train-dyn", "--data", "synth-arm", "--skel-run", str(phase1), "--preset", "tiny"]
    sequence = ["--set", "data.inputs=sequence"]
    assert nmjax_main([*argv, *sequence, "--run", str(tmp_path / "dyn")]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert f"nmjax export-keypoints --run {phase1}" in line
    assert not (tmp_path / "dyn").exists() and not list(phase1.glob("keypoints_*"))
    # "crop" inputs (the default) need the detector: its absence names both ways out.
    assert nmjax_main([*argv, "--run", str(tmp_path / "dyn")]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "no phase-1 detector checkpoint" in line and "inputs=sequence" in line
    assert not (tmp_path / "dyn").exists()
    assert nmjax_main([*argv, "--set", "data.inputs=video", "--run", str(tmp_path / "dyn")]) == 2
    assert "valid inputs: crop, sequence" in capsys.readouterr().err
    assert not (tmp_path / "dyn").exists()
