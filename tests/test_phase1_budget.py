"""experiments/phase1_budget.py: an unfinished run parked for the next machine comes back as it
was, and a finished one is not parked."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from experiment_scripts import load_experiment

from nmjax import run_folder
from nmjax.config_io import config_to_dict


@pytest.fixture
def budget(tmp_path, monkeypatch):
    module = load_experiment("phase1_budget.py")
    monkeypatch.setattr(module, "PARKED", tmp_path / "state")
    return module


def _fake_run(budget, root: Path, steps: list[int]) -> Path:
    """A run folder of the plan's first run with checkpoint folders of made-up contents."""
    body, recipe, seed = budget.PLAN[0]
    run = budget.run_dir(body, recipe, seed, root)
    (run / run_folder.CHECKPOINTS).mkdir(parents=True)
    config = config_to_dict(budget.run_config(body, recipe, seed))
    (run / run_folder.CONFIG_FILE).write_text(json.dumps(config))
    (run / run_folder.METRICS_FILE).write_text('{"step": 1}\n')
    for step in steps:
        item = run_folder.checkpoint_dir(run) / str(step) / "model"
        item.mkdir(parents=True)
        (item / "weights").write_bytes(bytes(range(step % 200)))
    return run


def test_an_unfinished_run_is_parked_and_restored_at_its_latest_step(budget, tmp_path):
    run = _fake_run(budget, tmp_path / "a", [1000, 2000, 2200])
    (written,) = budget.park(tmp_path / "a")
    assert written == budget.parked_state(run)
    elsewhere = tmp_path / "b" / run.name  # the next machine: no run folder
    assert budget.unpark(elsewhere)
    assert run_folder.checkpoint_steps(elsewhere) == [2200]
    restored = elsewhere / run_folder.CHECKPOINTS / "2200" / "model" / "weights"
    assert restored.read_bytes() == bytes(range(2200 % 200))
    assert (elsewhere / run_folder.CONFIG_FILE).read_text() == (
        run / run_folder.CONFIG_FILE
    ).read_text()
    assert not budget.unpark(elsewhere)  # it has checkpoints now: nothing to restore
    assert not list(elsewhere.parent.glob(".*"))  # no staging folder left behind


def test_a_finished_run_drops_its_parked_state(budget, tmp_path):
    run = _fake_run(budget, tmp_path / "a", [1000])
    budget.park(tmp_path / "a")
    assert budget.parked_state(run).is_file()
    last = run_folder.checkpoint_dir(run) / str(budget.STEPS)
    last.mkdir()
    assert budget.park(tmp_path / "a") == []
    assert not budget.parked_state(run).exists()


def test_a_folder_with_files_but_no_checkpoint_is_not_overwritten(budget, tmp_path):
    run = _fake_run(budget, tmp_path / "a", [1000])
    budget.park(tmp_path / "a")
    other = tmp_path / "b" / run.name
    other.mkdir(parents=True)
    (other / "notes.txt").write_text("mine")
    with pytest.raises(SystemExit, match="holds files but no checkpoint"):
        budget.unpark(other)
    assert (other / "notes.txt").read_text() == "mine"
