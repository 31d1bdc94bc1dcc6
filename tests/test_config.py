"""Tests of the configuration's shape: one `data` group in both phases, the presets as a table of
values pinned to what they were, config.json of every earlier layout read into today's, and one
command-line builder for both trainers."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from nmjax import run_folder
from nmjax.config import (
    DATASETS,
    PRESETS,
    DatasetConfig,
    DynTrainConfig,
    SkelTrainConfig,
    dyn_preset,
    skel_preset,
)
from nmjax.config_io import (
    apply_overrides,
    config_from_dict,
    config_to_dict,
    flatten_config,
    migrate,
    replace_fields,
    replace_paths,
)

LEGACY = Path(__file__).parent / "legacy_runs"
PHASES = {"skel": (SkelTrainConfig, skel_preset), "dyn": (DynTrainConfig, dyn_preset)}


# --- one data group ------------------------------------------------------------------------------


@pytest.mark.parametrize("phase", sorted(PHASES))
def test_both_phases_hold_the_same_data_group(phase):
    cls, preset = PHASES[phase]
    cfg = preset("synth-arm", "cpu")
    assert isinstance(cfg.data, DatasetConfig)
    base = {f.name for f in dataclasses.fields(DatasetConfig)}
    assert base == {"name", "root", "frames", "batch_size"}
    assert base <= set(flatten_config(cfg.data))
    assert (cfg.data.name, cfg.data.root) == ("synth-arm", None)
    moved = replace_paths(cfg, {"data.root": "/elsewhere", "data.batch_size": 8})
    assert (moved.data.root, moved.data.batch_size) == ("/elsewhere", 8)
    assert apply_overrides(cfg, ["data.batch_size=8", "data.root=/elsewhere"]) == moved
    # Where a run's data lives may change on a resume, its batch not, in both phases alike.
    run_folder.check_resume_config(cfg, replace_paths(cfg, {"data.root": "/elsewhere"}), "run")
    with pytest.raises(ValueError, match="data.batch_size"):
        run_folder.check_resume_config(cfg, moved, "run")


# --- the presets, pinned -------------------------------------------------------------------------


def _pinned() -> dict:
    """tests/legacy_runs/presets.json: every preset as config.json held it at ff7fd9e."""
    return json.loads((LEGACY / "presets.json").read_text())


@pytest.mark.parametrize("phase", sorted(PHASES))
@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_every_preset_is_the_one_it_was(phase, preset):
    cls, make = PHASES[phase]
    pinned = _pinned()[phase]
    assert sorted(pinned) == sorted(DATASETS)
    for data, presets in pinned.items():
        then = config_from_dict(cls, presets[preset], source=f"{phase}/{data}/{preset}")
        assert make(data, preset) == then, (data, preset)
        # Every field of the old file is in today's, at its new place, with its value.
        old = flatten_config(migrate(cls, presets[preset]))
        assert old.items() <= flatten_config(make(data, preset)).items()


def test_a_preset_is_values_over_the_datasets_own_configuration():
    tiny = PRESETS["tiny"]
    # The tiny preset's K is a value, not min(K, 6): every dataset has at least as many.
    assert all(spec.num_keypoints >= tiny.skel["model.num_keypoints"] for spec in DATASETS.values())
    own = skel_preset("synth-hand", "default")
    cpu = skel_preset("synth-hand", "cpu")
    changes = {**PRESETS["cpu"].skel, **PRESETS["cpu"].skel_per_data["synth-hand"]}
    assert cpu == replace_paths(own, changes)
    changed = {k for k, v in flatten_config(own).items() if flatten_config(cpu)[k] != v}
    assert changed <= set(changes)
    assert dyn_preset("aist", "tiny") == replace_paths(dyn_preset("aist"), PRESETS["tiny"].dyn)
    with pytest.raises(ValueError, match="valid presets: default, cpu, tiny"):
        skel_preset("synth-arm", "huge")
    with pytest.raises(ValueError, match="valid presets"):
        dyn_preset("synth-arm", "huge")


# --- config.json of every layout -----------------------------------------------------------------


def test_the_old_phase2_config_json_reads_into_the_data_group(tmp_path):
    # tests/legacy_runs/dyn/config.json: `"data": "synth-arm"`, frames, batch_size and inputs at
    # the top, as nmjax wrote it until the data group.
    old = json.loads((LEGACY / "dyn" / run_folder.CONFIG_FILE).read_text())
    assert old["data"] == "synth-arm" and {"frames", "batch_size", "inputs"} <= set(old)
    cfg = run_folder.load_config(LEGACY / "dyn", DynTrainConfig)
    assert (cfg.data.name, cfg.data.root, cfg.data.frames, cfg.data.batch_size) == (
        "synth-arm",
        None,
        6,
        4,
    )
    assert cfg.data.inputs == "sequence" and cfg.skel_run == "/tmp/legacy/skel"
    assert (cfg.loop.steps, cfg.loop.steps_per_epoch, cfg.model.latent) == (2, 7, 4)
    # Written back, it is today's layout, and reads back as itself.
    new = config_to_dict(cfg)
    assert new["data"] == {
        "name": "synth-arm",
        "root": None,
        "frames": 6,
        "batch_size": 4,
        "inputs": "sequence",
    }
    assert not {"frames", "batch_size", "inputs"} & set(new)
    assert migrate(DynTrainConfig, new) == new
    assert config_from_dict(DynTrainConfig, new) == cfg
    # Every old value is kept: the old keys, renamed, and the rest as they were.
    renamed = {"data": "data.name", **{k: f"data.{k}" for k in ("frames", "batch_size", "inputs")}}
    for key, value in flatten_config(old).items():
        assert flatten_config(new)[renamed.get(key, key)] == value, key


def test_a_flat_phase2_config_json_of_the_first_layout_reads_too():
    # Before the groups: the optimiser's and the loop's fields at the top as well.
    cfg = replace_fields(dyn_preset("synth-hand", "cpu"), steps=77, clip_norm=0.5)
    nested = config_to_dict(cfg)
    flat = {
        **{k: v for k, v in nested.items() if k not in ("data", "optim", "loop")},
        "data": "synth-hand",
        **{k: v for k, v in nested["data"].items() if k not in ("name", "root")},
        **nested["optim"],
        **nested["loop"],
    }
    assert config_from_dict(DynTrainConfig, flat) == cfg
    with pytest.raises(ValueError, match="bogus"):
        config_from_dict(DynTrainConfig, {**flat, "bogus": 1})
    # Phase 1 never had these at the top: there they are unknown fields.
    skel = config_to_dict(skel_preset("synth-arm"))
    with pytest.raises(ValueError, match="batch_size"):
        config_from_dict(SkelTrainConfig, {**skel, "batch_size": 4})


def test_phase2_old_spellings_still_set_the_data_group():
    cfg = dyn_preset("synth-arm", "tiny")
    dotted = apply_overrides(cfg, ["data.batch_size=8", "data.frames=9", "data.inputs=sequence"])
    assert apply_overrides(cfg, ["batch_size=8", "frames=9", "inputs=sequence"]) == dotted
    assert replace_fields(cfg, batch_size=8, frames=9, inputs="sequence") == dotted
    assert apply_overrides(cfg, ["data=synth-hand"]).data.name == "synth-hand"
    assert replace_fields(cfg, data="synth-hand").data.name == "synth-hand"
    whole = dataclasses.replace(cfg.data, name="synth-hand")
    assert replace_fields(cfg, data=whole).data == whole  # a group given whole
    with pytest.raises(ValueError, match="model is a group"):
        apply_overrides(cfg, ["model=nm"])
    with pytest.raises(ValueError, match="no field 'batch_size'"):
        apply_overrides(skel_preset("synth-arm", "tiny"), ["batch_size=8"])


# --- one command-line builder --------------------------------------------------------------------


def _config(phase: str, argv: list[str]):
    from nmjax.cli.train import train_config, train_parser

    return train_config(train_parser(phase).parse_args(argv), phase)


@pytest.mark.parametrize("phase", sorted(PHASES))
def test_the_shared_options_mean_the_same_in_both_phases(phase, data_root):
    argv = ["--data", "synth-arm", "--root", str(data_root), "--preset", "tiny"]
    argv += ["--batch-size", "4", "--seed", "2", "--steps", "8", "--run", "somewhere"]
    cfg = _config(phase, [*argv, "--set", "data.frames=5"])
    assert (cfg.data.name, cfg.data.root, cfg.data.batch_size, cfg.data.frames) == (
        "synth-arm",
        str(data_root),
        4,
        5,
    )
    assert (cfg.seed, cfg.run, cfg.loop.epochs, cfg.loop.steps) == (2, "somewhere", 0, 8)
    # --batch-size is --set data.batch_size, and --set comes after it.
    assert _config(phase, [*argv, "--set", "data.batch_size=6"]).data.batch_size == 6
    preset = PHASES[phase][1]("synth-arm", "tiny")
    assert _config(phase, ["--data", "synth-arm", "--preset", "tiny"]).data == preset.data
