"""The release's training recipe (docs/architecture.md §6b): epochs, learning rate and decays, no
clipping, and Adam restarted at every epoch boundary inside the compiled step."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from nmjax.config import (
    dyn_preset,
    resolve_epochs,
    skel_preset,
    steps_per_epoch,
    with_steps,
)
from nmjax.config_io import replace_fields
from nmjax.train import optim

# The release's train.py / dataset/config.py: (epochs, decay epochs) per dataset; the synthetic
# bodies take their real counterpart's.
RELEASE_EPOCHS = {
    "aist": (200, (60, 140)),
    "dfaust": (2000, (600, 1400)),
    "hanco": (200, (120, 170)),
    "animals": (200, (120, 170)),
    "panda": (200, (60, 140)),
    "synth-hand": (200, (120, 170)),
    "synth-arm": (200, (60, 140)),
    "synth-human": (200, (60, 140)),
    "synth-quadruped": (200, (120, 170)),
}


def test_steps_per_epoch_fills_the_last_batch():
    assert steps_per_epoch(27, 3) == 9
    assert steps_per_epoch(28, 3) == 10
    assert steps_per_epoch(27, 2) == 14
    assert steps_per_epoch(1, 3) == 1
    with pytest.raises(ValueError, match="sequence"):
        steps_per_epoch(0, 3)


@pytest.mark.parametrize("data", sorted(RELEASE_EPOCHS))
def test_default_preset_is_the_releases_recipe(data):
    cfg = skel_preset(data, "default")
    assert (cfg.loop.epochs, cfg.optim.decay_epochs) == RELEASE_EPOCHS[data]
    assert cfg.optim.learning_rate == 4e-4 and cfg.optim.lr_decay == (0.25, 0.1)
    assert cfg.optim.clip_norm == 0.0 and cfg.optim.optimizer_reset == "epoch"
    assert (cfg.data.batch_size, cfg.data.frames, cfg.model.grid) == (3, 10, 64)
    settings = optim.OptimizerSettings.of(resolve_epochs(cfg, 27, 3))
    assert settings.restart_period == 9 and settings.clip_norm == 0.0
    assert settings.milestones == tuple(9 * e for e in RELEASE_EPOCHS[data][1])


def test_resolve_epochs_fills_steps_and_milestones_once():
    cfg = skel_preset("aist", "default")
    resolved = resolve_epochs(cfg, 2461, 3)  # AIST++'s training sequences at B = 3
    assert resolved.loop.steps_per_epoch == 821
    assert resolved.loop.steps == 200 * 821 == 164_200
    assert resolved.optim.lr_milestones == (60 * 821, 140 * 821)
    # Resolved already (a resumed run): its steps stand, the data must still fit them.
    longer = resolve_epochs(replace_fields(resolved, steps=170_000), 2461, 3)
    assert longer.loop.steps == 170_000
    with pytest.raises(ValueError, match="steps per epoch"):
        resolve_epochs(resolved, 2000, 3)


def test_cpu_preset_trains_the_recipe_that_measured_better_on_two_cores():
    # experiments/results/recipe_ab.md: lr 1e-3, one Adam state, clipping at 1.0, 2,200 steps.
    for data in ("synth-arm", "synth-hand"):
        cfg = skel_preset(data, "cpu")
        assert (cfg.loop.epochs, cfg.loop.steps, cfg.optim.lr_milestones) == (0, 2200, (1400, 1900))
        assert (cfg.optim.learning_rate, cfg.optim.clip_norm, cfg.optim.optimizer_reset) == (
            1e-3,
            1.0,
            "never",
        )
        # a step count: no epochs to resolve
        assert resolve_epochs(cfg, 27, 2).loop.steps == 2200
    # The hand's per-body changes (recipe_ab.md, "Variants"); the arm has none.
    hand, arm = skel_preset("synth-hand", "cpu"), skel_preset("synth-arm", "cpu")
    assert (hand.weights.vol, hand.model.keypoint_temperature) == (10.0, 0.5)
    assert (arm.weights.vol, arm.model.keypoint_temperature) == (10.0, 1.0)
    assert skel_preset("synth-hand", "default").weights.vol == 0.1  # the paper's HanCo value
    # The paper's scale keeps the release's recipe.
    paper = skel_preset("synth-arm", "default")
    assert (paper.optim.learning_rate, paper.optim.clip_norm, paper.optim.optimizer_reset) == (
        4e-4,
        0.0,
        "epoch",
    )


def test_a_capture_trains_a_step_count_whatever_its_sequences():
    # A capture is one or a few sequences: an epoch would be one step, so the generic spec
    # counts 20,000 steps, decays at 30% and 70%, and one Adam state (none restarted per step).
    cfg = skel_preset("capture", "default")
    for sequences in (1, 2, 40):
        resolved = resolve_epochs(cfg, sequences, 3)
        assert (resolved.loop.epochs, resolved.loop.steps) == (0, 20_000)
        settings = optim.OptimizerSettings.of(resolved)
        assert settings.milestones == (6000, 14000) and settings.restart_period is None
        assert settings.learning_rate == 4e-4 and settings.clip_norm == 0.0
    assert (cfg.weights.vol, cfg.weights.traj, cfg.weights.local) == (10.0, 1.0, 1e-3)
    assert (cfg.model.num_keypoints, cfg.model.sigma_g, cfg.data.sample_rate) == (24, 1.5, 1)
    # The smaller presets are the same for a capture as for any body.
    cpu = skel_preset("capture", "cpu")
    assert (cpu.loop.steps, cpu.optim.lr_milestones) == (2200, (1400, 1900))
    assert skel_preset("capture", "tiny").loop.steps == skel_preset("synth-arm", "tiny").loop.steps


def test_a_step_count_keeps_the_decays_at_their_fractions():
    cfg = with_steps(skel_preset("synth-arm", "default"), 1000)
    assert (cfg.loop.epochs, cfg.loop.steps, cfg.optim.lr_milestones) == (0, 1000, (300, 700))
    cpu = with_steps(skel_preset("synth-arm", "cpu"), 1100)
    assert cpu.optim.lr_milestones == (700, 950)
    assert resolve_epochs(cfg, 27, 2).loop.steps == 1000  # no epochs to resolve


def _run(tx, grads):
    """Updates of `tx` on the gradient sequence `grads` (S, D), one jit-compiled update."""

    traces = []

    @jax.jit
    def update(g, state):
        traces.append(1)
        return tx.update(g, state, g)

    state, updates, states = tx.init(grads[0]), [], []
    for g in grads:
        u, state = update(g, state)
        updates.append(np.asarray(u))
        states.append(state)
    assert len(traces) == 1  # restarts happen inside the one compiled update
    return np.stack(updates), states


def test_learning_rate_on_both_sides_of_each_decay():
    # Constant gradients: Adam's normalised step is 1 in every coordinate, so |update| = rate,
    # with or without restarts.
    for period in (None, 0, 3):
        tx = optim.make_optimizer(0.1, (4, 7), (0.25, 0.1), restart_period=period)
        updates, _ = _run(tx, jnp.ones((9, 2)))
        np.testing.assert_allclose(
            np.abs(updates[:, 0]), [0.1] * 4 + [0.025] * 3 + [0.01] * 2, rtol=1e-4
        )


def test_adam_restarts_at_epoch_boundaries_and_not_inside():
    grads = jax.random.normal(jax.random.key(0), (7, 5))
    period = 3
    restarted, states = _run(optim.make_optimizer(1.0, restart_period=period), grads)
    plain, _ = _run(optim.make_optimizer(1.0), grads)
    fresh, _ = _run(optim.make_optimizer(1.0), grads[period:])
    # Inside the first epoch: the same as one Adam state; from step `period` on: a fresh Adam.
    np.testing.assert_allclose(restarted[:period], plain[:period], rtol=1e-6)
    np.testing.assert_allclose(restarted[period : 2 * period], fresh[:period], rtol=1e-5)
    # A first Adam step is -g / (|g| + eps): the sign of the gradient, at the next boundary too.
    np.testing.assert_allclose(restarted[2 * period], -np.sign(grads[2 * period]), rtol=1e-4)
    assert not np.allclose(restarted[period], plain[period])
    # The moments right after the boundary hold one gradient only: (1 - b1) g, (1 - b2) g^2.
    adam = states[period][0].inner
    np.testing.assert_allclose(adam.mu, 0.1 * grads[period], rtol=1e-5)
    np.testing.assert_allclose(adam.nu, 0.001 * grads[period] ** 2, rtol=1e-5)
    assert int(adam.count) == 1 and int(states[period - 1][0].inner.count) == period


def test_no_clipping_by_default_and_clipping_as_an_option():
    big = jnp.full((1, 4), 100.0)
    tx = optax.chain(optim.make_optimizer(1.0, clip_norm=1.0))
    assert optim.make_optimizer(1.0, clip_norm=0.0).init(big[0]) != tx.init(big[0])
    with pytest.raises(ValueError, match="period"):
        optim.restart_every(optax.scale_by_adam(), -1)
    # Epochs not counted yet: the restarting layout, no restart.
    never, _ = _run(optim.make_optimizer(1.0, restart_period=0), jnp.ones((4, 2)) * 3.0)
    np.testing.assert_allclose(never[-1], -1.0, rtol=1e-4)


@pytest.mark.parametrize("data", sorted(RELEASE_EPOCHS))
def test_phase2_default_is_the_releases_recipe(data):
    # The release's opt.pickle (AIST++): batch 16, T 20, 150 epochs, no decay, lr 4e-4, KL 0.003.
    cfg = dyn_preset(data, "default")
    assert (cfg.data.batch_size, cfg.data.frames, cfg.loop.epochs, cfg.kl_weight) == (
        16,
        20,
        150,
        0.003,
    )
    assert (
        cfg.optim.learning_rate == 4e-4
        and cfg.optim.clip_norm == 0.0
        and cfg.optim.optimizer_reset == "epoch"
    )
    resolved = resolve_epochs(cfg, 1227, cfg.data.batch_size)
    assert (resolved.loop.steps_per_epoch, resolved.loop.steps) == (77, 150 * 77)
    settings = optim.OptimizerSettings.of(resolved)
    assert settings.restart_period == 77 and settings.milestones == ()
