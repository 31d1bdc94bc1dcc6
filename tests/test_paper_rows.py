"""experiments/paper_phase1.py, paper_phase2.py and their table renderers: which rows are kept
across sessions, the plan, a phase-1 row and the phase-2 row on it trained and scored end to end
at the tiny size, and the tables rendered from rows."""

from __future__ import annotations

import dataclasses
import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from experiment_scripts import load_experiment

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def driver():
    return load_experiment("paper_phase1.py")


@pytest.fixture(scope="module")
def tables():
    return load_experiment("phase1_tables.py")


@pytest.fixture(scope="module")
def driver2(driver):
    # Loaded after paper_phase1.py, whose registered module it then imports and shares.
    return load_experiment("paper_phase2.py")


def _git(*args: str) -> str | None:
    done = subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True)
    return done.stdout.strip() if done.returncode == 0 else None


def _head() -> str | None:
    return _git("rev-parse", "HEAD")


def test_a_phase1_row_is_kept_only_when_made_by_code_that_computes_the_same_thing(driver):
    from nmjax.config_io import config_to_dict

    if _head() is None or not driver.descends_from(_head()):
        pytest.skip("needs this repository's git history (a clone with PHASE1_SINCE in it)")
    key = driver.RowKey("synth-arm", 1, "preset")
    cfg = driver.row_config(key)
    assert (cfg.seed, cfg.data.seed, cfg.run) == (1, 1, "runs/exp/skel-synth-arm-s1-preset")
    stamp = {"commit": _head(), "dirty": False, "metrics": driver.METRICS}
    row = {**dataclasses.asdict(key), "config": config_to_dict(cfg), "provenance": stamp}
    assert driver.same_computation(row, cfg)
    moved = {**row, "config": {**row["config"], "run": "elsewhere"}}  # the folder is no change
    assert driver.same_computation(moved, cfg)
    # A row stored before a field existed reads it at its default: `init_from` came later.
    older = {k: v for k, v in row["config"].items() if k != "init_from"}
    assert driver.same_computation({**row, "config": older}, cfg)
    tuned = {**row["config"], "init_from": "runs/other"}
    assert not driver.same_computation({**row, "config": tuned}, cfg)
    assert not driver.same_computation(
        row, driver.row_config(driver.RowKey("synth-arm", 0, "preset"))
    )
    assert not driver.same_computation({**row, "provenance": {**stamp, "dirty": True}}, cfg)
    redefined = {**stamp, "metrics": {**driver.METRICS, "sc": "another definition"}}
    assert not driver.same_computation({**row, "provenance": redefined}, cfg)
    before = subprocess.run(
        ["git", "rev-parse", f"{driver.PHASE1_SINCE}~1"], cwd=REPO, capture_output=True, text=True
    ).stdout.strip()
    assert not driver.same_computation({**row, "provenance": {**stamp, "commit": before}}, cfg)
    assert driver.same_computation(
        {**row, "provenance": {**stamp, "commit": driver.PHASE1_SINCE}}, cfg
    )


def test_every_variant_changes_one_thing(driver):
    base = driver.row_config(driver.RowKey("synth-human", 0, "preset"))
    changed = {
        "no_vol": lambda c: c.weights.vol == 0.0,
        "no_traj": lambda c: c.weights.traj == 0.0,
        "fan_in": lambda c: c.model.init == "fan_in",
    }
    for variant, check in changed.items():
        cfg = driver.row_config(driver.RowKey("synth-human", 0, variant))
        assert check(cfg) and not check(base), variant
        assert dataclasses.replace(cfg, weights=base.weights, model=base.model, run=base.run) == (
            dataclasses.replace(base, run=base.run)
        )
    with pytest.raises(ValueError, match="unknown variant"):
        driver.row_config(driver.RowKey("synth-arm", 0, "nope"))


def _row(body, seed, variant, jd, distinct, cd, sc=0.5):
    keep = [True, True, False, True]
    return {
        "body": body,
        "seed": seed,
        "variant": variant,
        "steps": 2200,
        "train_minutes": 10.0,
        "scores": {
            "sc": sc,
            "sc_std_over_joints": 0.1,
            "sc_fixed_nodes": sc + 0.01,
            "sc_fixed_nodes_std_over_joints": 0.1,
            "tracking_cd": cd,
            "tracking_cd_ci95": 1.5,
            "joint_distance": jd,
            "joint_distance_ci95": 0.01,
            "joint_coverage_0.05": 0.2,
            "joint_coverage_0.10": 0.4,
            "edge_precision": 0.5,
            "edge_precision_within_2_hops": 0.75,
            "bone_recall": 0.25,
            "distinct_nodes": distinct,
            "skeleton_kept_nodes": 3,
        },
        "pruned_parents": [0, 0, 1, 1],
        "keep": keep,
        "alg1_vs_filtered": {
            "algorithm1": {
                "edge_precision": 0.5,
                "edge_precision_within_2_hops": 0.75,
                "bone_recall": 0.25,
                "parents": [0, 0, 1, 1],
            },
            "filtered": {
                "edge_precision": 0.25,
                "edge_precision_within_2_hops": 0.5,
                "bone_recall": 0.25,
                "parents": [0, 0, 0, 1],
            },
        },
        "frame": {
            "keypoints": np.linspace(-0.5, 0.5, 16).reshape(4, 4).tolist(),
            "points": np.random.default_rng(0).uniform(-1, 1, (50, 3)).tolist(),
        },
        "provenance": {"commit": "0123456789abcdef", "dirty": False, "date": "2026-12-07"},
    }


def test_the_plan_runs_the_alternatives_second_seed_only_where_its_first_favours_it(driver):
    bodies = list(driver.BODIES)
    plan = driver.plan(bodies, [0, 1], ["preset", "comparisons", "alternative"], [])
    names = [k.name for k in plan]
    assert names[:8] == [f"{b}-s{s}-preset" for s in (0, 1) for b in bodies]
    assert {
        f"{b}-s0-{v}" for b in ("synth-human", "synth-hand") for v in ("gt", "no_vol", "no_traj")
    } <= set(names)
    assert len(names) == 8 + 6 + 4 + 4  # seed 1 of the alternative undecided: planned
    rows = [
        _row("synth-arm", 0, "preset", 0.2, 5, 30.0),
        _row("synth-arm", 0, "fan_in", 0.1, 8, 29.0),  # favours it
        _row("synth-hand", 0, "preset", 0.2, 5, 30.0),
        _row("synth-hand", 0, "fan_in", 0.3, 8, 29.0),  # farther joints: not
    ]
    names = [k.name for k in driver.plan(bodies, [0, 1], ["alternative"], rows)]
    assert "synth-arm-s1-fan_in" in names and "synth-hand-s1-fan_in" not in names


def test_tables_and_pictures_render_from_rows_and_name_the_missing_ones(tables, tmp_path):
    from nmjax import provenance

    rows = [_row(b, s, "preset", 0.2, 5, 30.0 + s) for b in tables.BODIES for s in (0, 1)]
    rows[0]["scores"]["sc"] = 0.812
    # A row scored by code that has the field's scores (the others predate them).
    field = {"cd_j2j": 12.5, "cd_j2b": 11.0, "cd_b2b": 10.25, "rig_fit_cd": 42.0}
    rows[1]["scores"] |= {**field, "rig_fit_cd_ci95": 3.5}
    for b in tables.BODIES[:3]:
        rows += [_row(b, s, "fan_in", 0.1, 8, 29.0) for s in (0, 1)]
    rows += [
        _row("synth-human", 0, "gt", 0.15, 6, 33.0),
        _row("synth-hand", 0, "no_vol", 0.3, 2, 50.0),
    ]
    tables.render(rows, tmp_path)
    t1 = (tmp_path / "table1_sc.md").read_text()
    assert "| synth-arm (Panda) | 0 | 0.812 (0.100) |" in t1 and "Rows not made" not in t1
    # The kept tree of every row is the chain 0-1-3 (node 2 pruned). synth-arm's true tree is a
    # chain of 9 joints forking into two chains of 2 (13 joints), synth-hand's a root with five
    # chains of 4 (21): deleting all but a chain of 3 nodes costs 10 and 18, and no script with
    # fewer edits removes that many nodes.
    arm = t1.split("| synth-arm (Panda) | 0 |")[1].split("\n")[0]
    assert arm.endswith("| 5 / 3 | 10 | not stored | not stored | 0123456 |")
    hand = t1.split("| synth-hand (HanCo) | 0 |")[1].split("\n")[0]
    assert "| 5 / 3 | 18 | not stored | not stored |" in hand
    arm1 = t1.split("| synth-arm (Panda) | 1 |")[1].split("\n")[0]
    assert "| 5 / 3 | 10 | 12.5 / 11 / 10.2 | 42 (3.5) |" in arm1
    assert "- not stored: not stored in the row" in t1
    table1 = json.loads((tmp_path / "table1_sc.json").read_text())["rows"]
    assert [r["tree_edit_distance"] for r in table1[:2]] == [10, 10]
    t2 = (tmp_path / "table2_tracking.md").read_text()
    assert "GT (L_vol -> joint MSE) | 33 (1.5) |" in t2 and "synth-hand-s0-gt" in t2
    t9 = (tmp_path / "table9_10_no_vol.md").read_text()
    assert "synth-human-s0-no_vol" in t9.split("Rows not made yet:")[1]
    assert "`[0, 0, '-', 1]`" in t9  # pruned node 2 shown as '-'
    init = (tmp_path / "init_alternative.md").read_text()
    assert "**Verdict: adopted.**" in init and "synth-quadruped: rows missing" in init
    alg1 = (tmp_path / "alg1_methods.md").read_text()
    assert f"at least the filtered rule's on {len(rows)} of {len(rows)} rows" in alg1
    assert json.loads((tmp_path / "table1_sc.json").read_text())["rows"][0]["scores"]["sc"] == 0.812
    for png in ("skeletons_cpu.png", "ltraj_ablation.png", "skeletons/synth-arm-s0-preset.png"):
        assert provenance.read_png(tmp_path / png)["metrics"], png
    # fan_in missing on the hand and the quadruped, its CD higher on the human at seed 1: one
    # body for, one against, two open: undecided; against on the arm too: not adopted.
    rows = [r for r in rows if not (r["body"] == "synth-hand" and r["variant"] == "fan_in")]
    fan_in = {(r["body"], r["seed"]): r for r in rows if r["variant"] == "fan_in"}
    fan_in["synth-human", 1]["scores"]["tracking_cd"] = 99.0
    verdict, reasons = tables.adoption(rows, [0, 1])
    assert verdict is None and "synth-human: not better at seed 1" in reasons
    fan_in["synth-arm", 0]["scores"]["distinct_nodes"] = 5  # no more than the preset's
    verdict, reasons = tables.adoption(rows, [0, 1])
    assert verdict is False and "synth-arm: not better at seed 0" in reasons


def _tiny(driver, root: Path, patch) -> None:
    """The tiny sizes in place of the cpu preset, and `root`'s data and runs, through `patch`
    (a pytest MonkeyPatch)."""
    from nmjax.config import skel_preset, with_steps

    patch.setenv("NMJAX_DATA", str(root / "data"))
    patch.setattr(driver.ec, "RUNS", root / "runs")
    patch.setattr(
        driver, "skel_preset", lambda body, preset: with_steps(skel_preset(body, "tiny"), 2)
    )


@pytest.fixture(scope="module")
def tiny_phase1(driver, tmp_path_factory) -> Path:
    """A folder with a tiny synth-arm dataset, runs/ and results/phase1_rows.json holding the
    seed-0 preset row at 2 steps of the tiny size, made by `paper_phase1.main`."""
    from nmjax.data import synthetic

    root = tmp_path_factory.mktemp("paper-rows")
    synthetic.generate(
        "synth-arm",
        root / "data" / "synth-arm",
        num_sequences=3,
        frames=12,
        points=1500,
        progress=False,
    )
    (root / "results").mkdir()
    with pytest.MonkeyPatch.context() as patch:
        _tiny(driver, root, patch)
        driver.main(PHASE1_ARGV + ["--rows", str(root / "results" / "phase1_rows.json")])
    return root


PHASE1_ARGV = ["--data", "synth-arm", "--seeds", "0", "--groups", "preset", "--allow-dirty"]


def test_a_tiny_phase1_row_is_trained_scored_written_and_not_trained_again(
    driver, tiny_phase1, monkeypatch
):
    _tiny(driver, tiny_phase1, monkeypatch)
    rows_file = tiny_phase1 / "results" / "phase1_rows.json"
    (row,) = driver.read_rows(rows_file)
    assert (row["body"], row["seed"], row["variant"], row["steps"]) == ("synth-arm", 0, "preset", 2)
    assert row["train_minutes"] > 0 and row["provenance"]["metrics"] == driver.METRICS
    s = row["scores"]
    assert {"sc", "tracking_cd", "joint_distance", "distinct_nodes", "bone_recall"} <= set(s)
    assert set(row["alg1_vs_filtered"]) == {"algorithm1", "filtered"}
    assert len(row["frame"]["keypoints"]) == len(row["keep"]) == 6
    assert (rows_file.parent / "table1_sc.md").is_file()
    assert (rows_file.parent / "skeletons" / "synth-arm-s0-preset.png").is_file()
    # A second call trains nothing: a clean checkout keeps the row as it is; a dirty one's row
    # is not kept, and the complete run folder is scored again without training.
    driver.main(PHASE1_ARGV + ["--rows", str(rows_file)])
    (again,) = driver.read_rows(rows_file)
    if row["provenance"]["dirty"] is False:
        assert again == row
    else:
        assert again["train_minutes"] is None and again["scores"] == s


def test_a_phase2_row_is_kept_only_when_made_by_code_that_computes_the_same_thing(driver2):
    from nmjax.config_io import config_to_dict

    head = _git("rev-parse", "HEAD")
    if head is None or not driver2.paper_phase1.descends_from(head, driver2.PHASE2_SINCE):
        pytest.skip("needs this repository's git history (a clone with PHASE2_SINCE in it)")
    skel = Path("runs/exp/skel-synth-arm-s0-preset")
    configs = {m: driver2.dyn_config("synth-arm", m, skel) for m in driver2.MODELS}
    assert configs["nm"].model.model == "nm" and configs["vrnn"].model.model == "vrnn"
    assert configs["nm"].run == "runs/exp/dyn-synth-arm-nm" and configs["nm"].data.inputs == "crop"
    source = {"row": "synth-arm-s0-preset", "commit": head, "run": str(skel)}
    stamp = {"commit": head, "dirty": False, "metrics": driver2.METRICS}
    row = {
        "body": "synth-arm",
        "phase1": source,
        "models": {m: {"config": config_to_dict(c)} for m, c in configs.items()},
        "settings": dict(driver2.SETTINGS),
        "provenance": stamp,
    }
    assert driver2.same_computation(row, configs, source)
    # The folders' paths, and steps_per_epoch (filled in from the data as training starts), are
    # no change.
    stored = row["models"]["nm"]["config"]
    moved = {
        **stored,
        "run": "elsewhere",
        "skel_run": "/abs/skel",
        "loop": {**stored["loop"], "steps_per_epoch": 2},
    }
    assert driver2.same_computation(
        {**row, "models": {**row["models"], "nm": {"config": moved}}}, configs, source
    )
    # A field added since the row was stored reads at its default.
    older = {k: v for k, v in row["models"]["nm"]["config"].items() if k != "init_from"}
    assert driver2.same_computation(
        {**row, "models": {**row["models"], "nm": {"config": older}}}, configs, source
    )
    heavier = {m: dataclasses.replace(c, kl_weight=1.0) for m, c in configs.items()}
    assert not driver2.same_computation(row, heavier, source)
    assert not driver2.same_computation(row, {"nm": configs["nm"]}, source)
    assert not driver2.same_computation(row, configs, {**source, "commit": "0" * 40})
    assert not driver2.same_computation(
        {**row, "settings": {**row["settings"], "samples": 3}}, configs, source
    )
    assert not driver2.same_computation(
        {**row, "provenance": {**stamp, "dirty": True}}, configs, source
    )
    redefined = {**stamp, "metrics": {**driver2.METRICS, "interpolation": "another"}}
    assert not driver2.same_computation({**row, "provenance": redefined}, configs, source)
    before = _git("rev-parse", f"{driver2.PHASE2_SINCE}~1")
    assert not driver2.same_computation(
        {**row, "provenance": {**stamp, "commit": before}}, configs, source
    )


def test_a_phase2_row_waits_for_its_phase1_row(driver2, tmp_path, capsys):
    rows1 = tmp_path / "phase1_rows.json"
    rows1.write_text('{"rows": []}')
    driver2.main(
        [
            "--data",
            "synth-arm",
            "--phase1-rows",
            str(rows1),
            "--rows",
            str(tmp_path / "p2.json"),
            "--dry-run",
        ]
    )
    out = capsys.readouterr().out
    assert "0 rows to make" in out and "waiting for the phase-1 row of synth-arm" in out


def test_a_tiny_phase2_row_is_trained_scored_rendered_and_not_trained_again(
    driver, driver2, tiny_phase1, monkeypatch
):
    from nmjax.config import dyn_preset

    _tiny(driver, tiny_phase1, monkeypatch)
    monkeypatch.setattr(driver2, "dyn_preset", lambda body, preset: dyn_preset(body, "tiny"))
    small = {
        "rates": [3],
        "trajectories": 2,
        "max_segments": 1,
        "horizons": [3],
        "samples": 2,
        "cond": 2,
        "clips": 1,
        "seed": 0,
    }
    monkeypatch.setattr(driver2, "SETTINGS", small)
    results = tiny_phase1 / "results"
    rows1, rows2 = results / "phase1_rows.json", results / "phase2_rows.json"
    argv = ["--data", "synth-arm", "--rows", str(rows2), "--phase1-rows", str(rows1)]
    (p1,) = driver.read_rows(rows1)
    driver2.main(argv + ["--allow-dirty"])  # also takes a phase-1 row of a dirty checkout
    (row,) = driver2.read_rows(rows2)
    assert row["phase1"] == {
        "row": "synth-arm-s0-preset",
        "commit": p1["provenance"]["commit"],
        "run": p1["run"],
    }
    assert set(row["models"]) == {"nm", "vrnn"} and row["settings"] == small
    for info in row["models"].values():
        assert info["train_minutes"] > 0 and info["config"]["loop"]["steps"] == 10
        assert any("val/recon" in r for r in info["curve"]) and info["final_validation"]
    assert set(row["interpolation"]) == {"Ours", "VRNN", "Lerp", "Slerp"}
    assert set(row["interpolation"]["Ours"]) == {"3"}
    assert set(row["generation"]["methods"]) == {"Ours", "VRNN", "Hold last pose"}
    for name in (
        "train_dyn_synth-arm.png",
        "train_dyn_synth-arm.json",
        "generation_synth-arm.md",
        "generation_synth-arm.png",
        "table11_12_synth-arm.png",
        "table11_12_keypoints.md",
    ):
        assert (results / name).is_file(), name
    table = (results / "table11_12_interpolation.md").read_text()
    assert "| Ours |" in table and "Lerp" in table
    assert "Not made yet: synth-hand, synth-human, synth-quadruped" in table
    # A second call trains nothing: a clean checkout keeps the row as it is; a dirty one's row
    # is not kept, and its complete runs are scored again without training.
    driver2.main(argv + ["--allow-dirty"])
    (again,) = driver2.read_rows(rows2)
    if row["provenance"]["dirty"] is False:
        assert again == row
    else:
        assert all(m["train_minutes"] is None for m in again["models"].values())
        assert again["interpolation"] == row["interpolation"]
