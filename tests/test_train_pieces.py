"""Tests of the trainers' shared pieces: the optimizer schedule (`train.optim`), run folders
(`run_folder`), checkpoints (`train.checkpoints`), metric logs (`train.metric_log`)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import grain
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from flax import nnx

from nmjax import run_folder
from nmjax.config import DetectorConfig, LoopConfig, SkelTrainConfig
from nmjax.config_io import config_from_dict, config_to_dict, replace_fields
from nmjax.train import checkpoints, metric_log, optim


def _adam_lr(tx, grads_seq):
    """Applies `tx` to a scalar parameter with unit gradients; returns the update magnitudes."""
    params = jnp.zeros(())
    state = tx.init(params)
    sizes = []
    for g in grads_seq:
        updates, state = tx.update(jnp.asarray(g), state, params)
        sizes.append(float(-updates))
    return np.array(sizes)


def test_optimizer_schedule_factors_of_initial_rate():
    tx = optim.make_optimizer(0.1, milestones=(3, 5), decay=(0.25, 0.1), clip_norm=None)
    # With a constant gradient, Adam's normalised step equals the learning rate.
    sizes = _adam_lr(tx, [1.0] * 7)
    np.testing.assert_allclose(sizes, [0.1] * 3 + [0.025] * 2 + [0.01] * 2, rtol=1e-4)


def test_optimizer_clips_global_norm():
    tx = optim.make_optimizer(1.0, clip_norm=1.0)
    grads = {"a": jnp.array([3.0, 4.0]), "b": jnp.array([12.0])}  # global norm 13
    _, state = tx.update(grads, tx.init(grads), grads)
    mu = optax.tree_utils.tree_get(state, "mu")
    # Adam's first moment after one step is (1 - b1) times the clipped gradient g / 13.
    np.testing.assert_allclose(mu["a"], 0.1 * np.array([3.0, 4.0]) / 13.0, rtol=1e-6)
    np.testing.assert_allclose(mu["b"], 0.1 * np.array([12.0]) / 13.0, rtol=1e-6)


@pytest.mark.parametrize(
    ("milestones", "decay"), [((5,), (0.1, 0.2)), ((5, 3), (0.5, 0.1)), ((3,), (-1.0,))]
)
def test_optimizer_rejects_bad_schedule(milestones, decay):
    with pytest.raises(ValueError, match="lr_"):
        optim.make_optimizer(1e-3, milestones, decay, 1.0)


def test_weight_average_is_the_bias_corrected_ema_of_the_updated_weights():
    """apply_gradients keeps optax.ema of the weights after each update; trained_model hands out
    its bias-corrected value (sum_i (1-d) d^(n-i) w_i / (1 - d^n)); without it, the weights."""
    decay = 0.6
    settings = optim.OptimizerSettings(0.1, clip_norm=None, ema_decay=decay)
    graphdef, state = optim.init_state(nnx.Linear(2, 1, rngs=nnx.Rngs(0)), settings)
    grads_seq = [1.0, -2.0, 0.5]
    weights = []
    for g in grads_seq:
        model = nnx.merge(graphdef, state["model"])
        grads = jax.tree.map(lambda x, g=g: jnp.full_like(x, g), nnx.state(model, nnx.Param))
        state = optim.apply_gradients(model, grads, state, settings)
        weights.append(np.asarray(state["model"]["kernel"][...]))
    n = len(weights)
    expected = sum((1 - decay) * decay ** (n - 1 - i) * w for i, w in enumerate(weights))
    expected /= 1 - decay**n
    averaged = optim.trained_model(graphdef, state, decay)
    np.testing.assert_allclose(averaged.kernel[...], expected, rtol=1e-5)
    assert not np.allclose(expected, weights[-1])  # the average is not the last weights
    plain = optim.OptimizerSettings(0.1, clip_norm=None)
    _, plain_state = optim.init_state(nnx.Linear(2, 1, rngs=nnx.Rngs(0)), plain)
    assert "ema" not in plain_state
    np.testing.assert_array_equal(
        optim.trained_model(graphdef, plain_state, 0.0).kernel[...],
        plain_state["model"]["kernel"][...],
    )


def test_config_round_trip():
    cfg = replace_fields(
        SkelTrainConfig(model=DetectorConfig(hourglass_channels=(4, 5, 6))), steps=7
    )
    back = config_from_dict(SkelTrainConfig, config_to_dict(cfg))
    assert back == cfg
    with pytest.raises(ValueError, match="bogus"):
        config_from_dict(SkelTrainConfig, {"bogus": 1})


def test_prepare_run_dir(tmp_path):
    cfg = replace_fields(SkelTrainConfig(), steps=3)
    run = run_folder.prepare_run_dir(tmp_path / "run", resume=False, config=cfg)
    assert json.loads((run / "config.json").read_text())["loop"]["steps"] == 3
    assert run_folder.load_config(run, SkelTrainConfig) == cfg
    (run / "keep.txt").write_text("x")
    with pytest.raises(ValueError, match="--resume"):
        run_folder.prepare_run_dir(run, resume=False, config=cfg)
    assert (run / "keep.txt").exists()
    # resuming needs a complete checkpoint; refused before anything in the folder changes
    with pytest.raises(FileNotFoundError, match="no complete checkpoint"):
        run_folder.prepare_run_dir(run, resume=True, config=cfg)
    assert (run / "keep.txt").exists()
    run_folder.prepare_run_dir(run, resume=False, config=cfg, overwrite=True)
    assert not (run / "keep.txt").exists()
    with pytest.raises(FileNotFoundError, match="missing"):
        run_folder.prepare_run_dir(tmp_path / "missing", resume=True, config=cfg)


def _state(features: int, seed: int = 0):
    """A training state {"model", "opt"} as the trainers save it."""
    model = nnx.Linear(3, features, rngs=nnx.Rngs(seed))
    opt = optim.make_optimizer(1e-3).init(nnx.state(model, nnx.Param))
    return {"model": nnx.state(model), "opt": opt}


def _abstract(state):
    return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), state)


def test_checkpointer_keeps_latest_and_best_and_restores_iterator(tmp_path):
    dataset = grain.MapDataset.range(50).shuffle(seed=1).to_iter_dataset()
    it = iter(dataset)
    states = {step: _state(4, seed=step) for step in range(1, 6)}
    val = {1: 3.0, 2: 1.0, 3: 2.0}
    with checkpoints.Checkpointer(tmp_path / "ckpt", keep=2, best_metric="val_loss") as ckpt:
        for step, state in states.items():
            next(it)
            metrics = {"val_loss": val[step]} if step in val else None
            ckpt.save(step, state, metrics=metrics, data_iter=it)
        assert ckpt.all_steps() == [2, 4, 5]
        assert ckpt.best_step() == 2
        assert ckpt.latest_step() == 5
        with pytest.raises(ValueError, match="overwrite"):
            ckpt.save(5, states[5])
        fresh = iter(dataset)
        step, restored = ckpt.restore(_abstract(states[1]), step=2, data_iter=fresh)
    assert step == 2
    for a, b in zip(jax.tree.leaves(restored), jax.tree.leaves(states[2]), strict=True):
        np.testing.assert_array_equal(a, b)
    # The restored iterator continues where the saved one stood after two elements.
    reference = iter(dataset)
    expected = [next(reference) for _ in range(3)][-1]
    assert next(fresh) == expected


def test_checkpointer_keeps_every_nth_step_for_good(tmp_path):
    """keep_every keeps the multiples of it beside the latest; a reopened manager with the
    loop's policy (`of_run`) deletes none of them when it saves again."""
    loop = LoopConfig(keep_checkpoints=1, keep_every=2)
    with checkpoints.Checkpointer.of_run(tmp_path, loop) as ckpt:
        for step in range(1, 6):
            ckpt.save(step, _state(4, seed=step))
        assert ckpt.all_steps() == [2, 4, 5]
    with checkpoints.Checkpointer.of_run(tmp_path, loop) as ckpt:
        ckpt.save(7, _state(4))
        assert ckpt.all_steps() == [2, 4, 7]
    with pytest.raises(ValueError, match="keep_every"):
        checkpoints.Checkpointer(tmp_path / "other", keep=1, keep_every=-1)


_RESTORE_SCRIPT = """
import sys, jax
from flax import nnx
from nmjax import config, run_folder
from nmjax.train import checkpoints, metric_log, optim
model = nnx.Linear(3, 4, rngs=nnx.Rngs(0))
opt = optim.make_optimizer(1e-3).init(nnx.state(model, nnx.Param))
state = {"model": nnx.state(model), "opt": opt}
abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), state)
try:
    checkpoints.Checkpointer(sys.argv[1], keep=2).restore(abstract)
except ValueError as err:
    print("ValueError:", err)
"""


def test_checkpointer_incompatible_and_corrupt(tmp_path):
    with checkpoints.Checkpointer(tmp_path / "ckpt", keep=2) as ckpt:
        ckpt.save(1, _state(4))
        with pytest.raises(ValueError, match="configuration"):
            ckpt.restore(_abstract(_state(5)))
        with pytest.raises(FileNotFoundError, match="available steps"):
            ckpt.restore(_abstract(_state(4)), step=9)
    files = [p for p in (tmp_path / "ckpt" / "1").rglob("*") if p.is_file()]
    array_files = [p for p in files if p.parent.name == "d"]  # ocdbt data blobs
    assert array_files
    for p in array_files:
        p.write_bytes(b"garbage")
    before = {p: p.read_bytes() for p in files}
    # A failed restore leaves orbax's in-flight tensorstore reads calling into a closed event loop
    # (reported as unraisable exceptions at a random later time), so it runs in its own process
    # (with no time limit: a loaded machine may take long to start it).
    result = subprocess.run(
        [sys.executable, "-c", _RESTORE_SCRIPT, str(tmp_path / "ckpt")],
        capture_output=True,
        text=True,
        env={**os.environ, "JAX_PLATFORMS": "cpu"},
        check=True,
    )
    assert "ValueError: checkpoint 1" in result.stdout
    assert "corrupt" in result.stdout
    assert {p: p.read_bytes() for p in files} == before


def test_metric_writer_jsonl_tensorboard_and_resume(tmp_path):
    writer = metric_log.MetricWriter(tmp_path)
    for step in (1, 2, 3):
        writer.write_scalars(step, {"loss": jnp.float32(step * 0.5), "lr": 1e-3})
    writer.close()
    records = metric_log.read_metrics(tmp_path)
    assert [r["step"] for r in records] == [1, 2, 3]
    assert records[1]["loss"] == pytest.approx(1.0)
    assert any((tmp_path / "tb").iterdir())
    writer = metric_log.MetricWriter(tmp_path, resume_step=2)
    writer.write_scalars(3, {"loss": 9.0})
    writer.close()
    records = metric_log.read_metrics(tmp_path)
    assert [(r["step"], r["loss"]) for r in records] == [(1, 0.5), (2, 1.0), (3, 9.0)]
