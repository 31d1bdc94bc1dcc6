"""Tests of nmjax.train.trained: a trained model restored for inference without its optimizer,
runs of the earlier checkpoint layout, the inference batch as an argument."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import jax
import numpy as np
import pytest
from flax import nnx

from nmjax import run_folder
from nmjax.cli import main as nmjax_main
from nmjax.config import SkelTrainConfig
from nmjax.train import checkpoints, optim, skel, trained

LEGACY = Path(__file__).parent / "legacy_runs"


@pytest.fixture
def legacy_runs(tmp_path):
    """A copy of tests/legacy_runs with the phase-2 run pointing at its own phase-1 run."""
    for name in ("skel", "dyn"):
        shutil.copytree(LEGACY / name, tmp_path / name)
    config = json.loads((tmp_path / "dyn" / run_folder.CONFIG_FILE).read_text())
    config["skel_run"] = str(tmp_path / "skel")
    (tmp_path / "dyn" / run_folder.CONFIG_FILE).write_text(json.dumps(config))
    return tmp_path, np.load(LEGACY / "expected.npz")


def test_a_legacy_detector_restores_to_the_keypoints_it_gave(legacy_runs):
    root, expected = legacy_runs
    detector = trained.Detector.load(root / "skel")
    np.testing.assert_allclose(
        detector.keypoints(expected["voxels"]), expected["keypoints"], rtol=1e-5, atol=1e-6
    )


def test_a_legacy_dynamics_model_restores_to_its_parameters(legacy_runs):
    root, expected = legacy_runs
    model = trained.restore_dynamics(root / "dyn")
    params = {
        "dyn" + jax.tree_util.keystr(path): np.asarray(leaf)
        for path, leaf in jax.tree_util.tree_leaves_with_path(nnx.state(model, nnx.Param))
    }
    wanted = {k: expected[k] for k in expected.files if k.startswith("dyn")}
    assert params.keys() == wanted.keys()
    for key, value in wanted.items():
        np.testing.assert_array_equal(params[key], value, err_msg=key)


def test_a_legacy_checkpoint_resumes_whole(legacy_runs):
    # Training restores every part; from the one-item layout it gets them all back, optimizer
    # state included (the step counter Adam keeps).
    root, _ = legacy_runs
    cfg = run_folder.load_config(root / "skel", SkelTrainConfig)
    _, state = skel.build(cfg)
    with checkpoints.Checkpointer.of_run(root / "skel", cfg.loop) as ckpt:
        step, restored = ckpt.restore(checkpoints.abstract_state(state))
        with pytest.raises(ValueError, match="whole training state"):
            ckpt.restore_parts({"model": checkpoints.abstract_state(state["model"])})
    assert step == 2 and restored.keys() == state.keys()
    counts = [np.asarray(x) for x in jax.tree.leaves(restored["opt"]) if np.ndim(x) == 0]
    assert counts and all(int(c) == 2 for c in counts if np.issubdtype(c.dtype, np.integer))


def test_a_new_checkpoint_holds_each_part_and_inference_builds_no_optimizer(
    legacy_runs, tmp_path, monkeypatch
):
    # Re-save the legacy run's state in today's layout, then restore the detector with the
    # optimizer's construction made to fail: inference must not need it.
    root, expected = legacy_runs
    cfg = run_folder.load_config(root / "skel", SkelTrainConfig)
    _, state = skel.build(cfg)
    with checkpoints.Checkpointer.of_run(root / "skel", cfg.loop) as ckpt:
        _, restored = ckpt.restore(checkpoints.abstract_state(state))
    new = tmp_path / "new"
    shutil.copytree(root / "skel", new, ignore=shutil.ignore_patterns("checkpoints"))
    with checkpoints.Checkpointer.of_run(new, cfg.loop, trained.BEST_METRIC) as ckpt:
        ckpt.save(2, restored, metrics={trained.BEST_METRIC: 1.0})
    step_dir = run_folder.checkpoint_dir(new) / "2"
    assert {"model", "opt"} <= {p.name for p in step_dir.iterdir()}
    assert not (step_dir / checkpoints.LEGACY_STATE_ITEM).exists()

    def no_optimizer(self):
        raise AssertionError("inference built an optimizer")

    monkeypatch.setattr(optim.OptimizerSettings, "make", no_optimizer)
    detector = trained.Detector.load(new)
    np.testing.assert_allclose(
        detector.keypoints(expected["voxels"]), expected["keypoints"], rtol=1e-5, atol=1e-6
    )


def test_the_inference_batch_is_an_argument(legacy_runs):
    root, expected = legacy_runs
    voxels = expected["voxels"]
    one = trained.Detector.load(root / "skel", batch_size=1)
    assert one.batch_size == 1 and one.cfg.data.batch_size == 2  # the config is left alone
    three = one.with_batch_size(3)  # pads 2 crops to 3
    np.testing.assert_allclose(one.keypoints(voxels), three.keypoints(voxels), atol=1e-6)
    with pytest.raises(ValueError, match=">= 1"):
        one.with_batch_size(0)


def test_a_legacy_phase2_run_resumes_from_its_old_config_json(legacy_runs, capsys):
    # Its config.json is the first phase-2 layout ("data": "synth-arm", frames, batch_size and
    # inputs at the top). `--resume` reads it into the data group, accepts the run's own
    # configuration, trains on, and writes config.json back in today's layout.
    root, _ = legacy_runs
    skel_run, dyn_run = root / "skel", root / "dyn"
    rng = np.random.default_rng(0)
    k = run_folder.read_skeleton(skel_run).num_keypoints
    for split, count in (("train", 27), ("test", 3)):  # 27 sequences: 7 steps an epoch at B=4
        walks = np.cumsum(rng.normal(scale=0.02, size=(count, 12, k, 4)), axis=1) + 0.5
        run_folder.write_trajectories(
            run_folder.keypoints_file(skel_run, split), {f"s{i}": w for i, w in enumerate(walks)}
        )
    old = json.loads((dyn_run / run_folder.CONFIG_FILE).read_text())
    argv = ["train-dyn", "--resume", "--run", str(dyn_run), "--steps", "3", "--no-progress"]
    assert nmjax_main(argv) == 0, capsys.readouterr().err
    assert run_folder.checkpoint_steps(dyn_run)[-1] == 3
    new = json.loads((dyn_run / run_folder.CONFIG_FILE).read_text())
    assert new["data"] == {
        "name": "synth-arm",
        "root": None,
        "frames": 6,
        "batch_size": 4,
        "inputs": "sequence",
    }
    assert new["loop"] == {**old["loop"], "steps": 3}
    assert {k: v for k, v in new.items() if k not in ("data", "loop", "run")} == {
        k: v
        for k, v in old.items()
        if k not in ("data", "frames", "batch_size", "inputs", "loop", "run")
    }
