"""experiments/phase1_study.py: every variant builds a configuration that can train, and the
cpu preset adopts only measured variants."""

from __future__ import annotations

from pathlib import Path

import pytest
from experiment_scripts import load_experiment

from nmjax.config_io import replace_fields


@pytest.fixture
def study(tmp_path, monkeypatch):
    """The script as a module, with $NMJAX_DATA on a 3-sequence synth-arm set; bigger sets are
    recorded, not generated."""
    from nmjax.data import synthetic

    synthetic.generate(
        "synth-arm", tmp_path / "synth-arm", num_sequences=3, frames=12, points=1500, progress=False
    )
    monkeypatch.setenv("NMJAX_DATA", str(tmp_path))
    module = load_experiment("phase1_study.py")
    generated = []
    real = synthetic.ensure_dataset

    def ensure(name, root=None, **options):
        if options:
            generated.append((name, Path(root).name, options))
            return Path(root)
        return real(name, root)

    monkeypatch.setattr(module.synthetic, "ensure_dataset", ensure)
    module.generated = generated
    return module


def test_every_variant_is_a_valid_config_with_its_change(study):
    from nmjax.train import skel

    base = study.variant_config("synth-arm", "base", 12.0, 3)
    assert base.seed == 3 and base.data.seed == 3 and base.loop.time_limit_minutes == 12.0
    for name in study.VARIANTS:
        cfg = study.variant_config("synth-arm", name, 12.0, 0, steps=50)
        skel.check_config(cfg)
        assert cfg.loop.steps == 50 and cfg.loop.time_limit_minutes == 0.0, name
    assert study.variant_config("synth-arm", "sigma_paper", 1, 0).model.sigma_g == 0.75
    gt = study.variant_config("synth-arm", "gt_stride2", 1, 0)
    assert gt.model.num_keypoints == 13 and gt.weights.vol_target == "joints"  # K = J
    assert gt.model.heatmap_stride == 2
    big = study.variant_config("synth-arm", "data10x_vol10", 1, 0)
    assert Path(big.data.root).name == "synth-arm-n300-seed1" and big.weights.vol == 10.0
    assert ("synth-arm", "synth-arm-n300-seed1", {"num_sequences": 300, "seed": 1}) in (
        study.generated
    )
    with pytest.raises(SystemExit, match="unknown variant"):
        study.variant_config("synth-arm", "nope", 1, 0)


def test_base_variant_is_the_cpu_preset_counted_in_steps(study):

    from nmjax.config import skel_preset, with_steps

    base = study.variant_config("synth-hand", "base", 12.0, 0)
    preset = skel_preset("synth-hand", "cpu")
    assert base == replace_fields(with_steps(preset, 100_000), time_limit_minutes=12.0, seed=0)
    # The hand's cpu preset carries its body changes (`Preset.skel_per_data`).
    assert base.loop.epochs == 0 and (base.weights.vol, base.model.keypoint_temperature) == (
        10.0,
        0.5,
    )
    fixed = study.variant_config("synth-arm", "vol10_temp0.5", 0.0, 1, steps=600)
    assert (fixed.loop.steps, fixed.loop.time_limit_minutes, fixed.seed) == (600, 0.0, 1)
    assert (fixed.weights.vol, fixed.model.keypoint_temperature) == (10.0, 0.5)


def test_report_carries_the_skeleton_measures_and_marks_rows_written_before_them(
    study, tmp_path, monkeypatch
):
    import json

    # A row written before the skeleton measures existed (the archived study, earlier network).
    committed = json.loads((study.RESULTS / "archive" / "phase1_study.json").read_text())
    old = committed[0]
    results = {
        "joint_distance": {"mean": 0.0812, "ci95": 0.004, "n": 3, "per_sequence": {}},
        "joint_coverage_0.05": 0.25,
        "joint_coverage_0.10": 0.5,
        "edge_precision": 0.75,
        "edge_precision_within_2_hops": 1.0,
        "bone_recall": 0.6,
        "distinct_nodes": 7,
        "skeleton_kept_nodes": 9,
    }
    measures = study.skeleton_measures(results)
    assert measures["joint_distance"] == 0.0812 and measures["joint_distance_ci95"] == 0.004
    assert measures["distinct_nodes"] == 7 and measures["skeleton_kept_nodes"] == 9
    assert study.skeleton_measures({})["edge_precision"] is None  # data without joints
    new = {k: v for k, v in old.items() if k not in ("joint_distance", "distinct_nearest")}
    stamp = {"commit": "0123456789abcdef", "dirty": False, "changed": 0}
    new = {**new, "variant": "new", **measures, "provenance": stamp}
    monkeypatch.setattr(study, "RESULTS", tmp_path)
    study.write_report([old, new])
    text = (tmp_path / "phase1_study.md").read_text()
    assert "## Provenance" in text and "commit 0123456789 (clean))" in text
    assert f"commit {old.get('commit') or 'n/a'})" in text  # a row from before the stamp
    table = text.splitlines()
    header = next(line for line in table if line.startswith("| body |"))
    old_line = next(
        line for line in table if line.startswith(f"| {old['data']} | {old['variant']}")
    )
    new_line = next(line for line in table if line.startswith(f"| {new['data']} | new |"))
    columns = [c.strip() for c in header.split("|")]
    assert len(columns) == len(new_line.split("|")) == len(old_line.split("|"))
    cell = dict(zip(columns, (c.strip() for c in new_line.split("|")), strict=True))
    assert (cell["joint d"], cell["cov .05"], cell["edge 2h"], cell["distinct"]) == (
        "0.081",
        "0.250",
        "1.000",
        "7",
    )
    cell = dict(zip(columns, (c.strip() for c in old_line.split("|")), strict=True))
    assert cell["joint d"] == f"{old['joint_distance']:.3f}*" and cell["edge"] == "n/a"
    assert cell["distinct"] == f"{old['distinct_nearest']}*"
    assert json.loads((tmp_path / "phase1_study.json").read_text())[1]["bone_recall"] == 0.6
