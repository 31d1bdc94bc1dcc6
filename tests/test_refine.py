"""The articulated refinement after phase 1 (`nmjax.skeleton_refine`, `nmjax.export.refine`,
`nmjax refine`): it lowers the rig's fit error, keeps every bone's length, runs under jit and
vmap, writes a refined skeleton that reads back, and refuses bad inputs in one line."""

from __future__ import annotations

import json
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from experiment_scripts import load_experiment
from tiny_runs import ORDER, PARENTS, make_skel_run

from nmjax import geometry, metrics, provenance, run_folder
from nmjax import skeleton_refine as sr
from nmjax.cli import main as nmjax_main
from nmjax.data import synthetic
from nmjax.data.bodies import get_body
from nmjax.data.normalize import normalize_sequence
from nmjax.export.refine import refine_run, refine_sequence, unrefined_rig
from nmjax.export.sources import kept_skin_weights

# A short budget on few points: enough for the fit to move, quick to compile and run.
TINY = sr.RefineSettings(iterations=40, surface_points=192, target_points=192)


def arm_case(frames: int = 8, noise: float = 0.03, seed: int = 0, body: str = "synth-arm"):
    """A synthetic body's motion with known joints (synth-arm unless `body`): its points
    (T, N, 3) and joints (T, J, 3) in the sequence's cube, keypoints (T, J, 4) = the joints plus
    seeded noise (bones that change length, as phase 1's do), and the true tree (every node
    kept)."""
    seq = synthetic.simulate(body, frames, points=600, rng=seed)
    points, joints = normalize_sequence(seq.vertices, seq.joints)
    noisy = joints + np.random.default_rng(seed).normal(scale=noise, size=joints.shape)
    keypoints = np.concatenate([noisy, np.ones((*joints.shape[:2], 1))], axis=-1)
    parents = np.asarray(get_body(body).parents)
    return points, joints, keypoints.astype(np.float32), (parents, np.ones(len(parents), bool))


def bone_lengths_over_time(positions: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """(T, J) length of every joint's bone in every frame."""
    return np.linalg.norm(positions - positions[:, parents], axis=-1)


@pytest.fixture(scope="module")
def refined_arm():
    points, joints, keypoints, skeleton = arm_case()
    arrays, errors = refine_sequence(keypoints, points, skeleton, 1.0, TINY, progress=False)
    return points, joints, keypoints, skeleton, arrays, errors


# --- the math -------------------------------------------------------------------------------


def test_the_refinement_lowers_the_fit_error(refined_arm):
    _, _, _, _, arrays, errors = refined_arm
    assert errors["fit_after"] < 0.8 * errors["fit_before"], errors
    assert errors["fit_after_capture"] < errors["fit_before_capture"]
    history = arrays["chamfer_history"]
    assert history.shape == (TINY.iterations,) and np.all(np.isfinite(history))
    assert history[-5:].mean() < 0.8 * history[:5].mean()
    # The reported error is `metrics.rig_fit_error` of the stored surface, weights and motion.
    skinned = sr.skin(
        arrays["positions"],
        arrays["rotations"],
        arrays["rest_positions"],
        arrays["weights"],
        arrays["surface"],
    )
    points = refined_arm[0]
    again = metrics.rig_fit_error(skinned, points, 1.0)["cd"]
    np.testing.assert_allclose(again, errors["fit_after"], rtol=1e-4)


def test_every_bone_keeps_its_length_in_every_frame(refined_arm):
    _, _, keypoints, skeleton, arrays, _ = refined_arm
    parents = arrays["parents"]
    lengths = bone_lengths_over_time(arrays["positions"], parents)
    # Every frame's bone is the rest offset turned by a rotation: its length, to float32.
    offsets = np.linalg.norm(arrays["offsets"], axis=-1)
    offsets[parents == np.arange(len(parents))] = 0.0
    np.testing.assert_allclose(lengths, np.broadcast_to(offsets, lengths.shape), atol=1e-6)
    assert np.max(lengths.std(axis=0)) < 1e-6
    ones = np.ones((*arrays["positions"].shape[:2], 1), np.float32)
    variation = metrics.bone_length_variation(
        np.concatenate([arrays["positions"], ones], axis=-1), parents, kept=np.ones(len(parents))
    )
    assert float(variation) < 1e-6
    # The keypoints' bones did change length; the rotations are rotations.
    before = bone_lengths_over_time(keypoints[..., :3], skeleton[0])
    assert np.max(before.std(axis=0)) > 1e-3
    rot = arrays["rotations"].astype(np.float64)
    np.testing.assert_allclose(rot @ np.swapaxes(rot, -1, -2), np.eye(3) + 0 * rot, atol=1e-5)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-5)


def test_the_refined_rotations_gain_a_twist_the_swing_rotations_lack(refined_arm):
    points, _, keypoints, skeleton, arrays, _ = refined_arm
    rig = unrefined_rig("arm", keypoints, skeleton, 30.0)
    # A swing rotation turns the rest bone onto the bone by the smallest rotation: its axis is
    # normal to the rest bone. The refined rotations are free about the bone as well.
    rest_bone = rig.rest_positions - rig.rest_positions[rig.parents]
    refined_axes = []
    for rotations in (rig.rotations, arrays["rotations"].astype(np.float64)):
        quat = np.asarray(geometry.matrix_to_quaternion(jnp.asarray(rotations)))
        along = np.abs(np.sum(quat[..., 1:] * rest_bone, axis=-1))  # sin(angle/2) x along bone
        refined_axes.append(along[:, 1:].max())
    assert refined_axes[0] < 1e-5 < refined_axes[1]


def test_initial_params_reproduce_the_unrefined_rig_of_rigid_bones():
    # Keypoints whose bones keep their lengths (synth-human's joints only rotate; the arm's
    # fingers slide): the start is the swing rig itself.
    points, joints, _, skeleton = arm_case(frames=5, body="synth-human")
    keypoints = np.concatenate([joints, np.ones((*joints.shape[:2], 1), np.float32)], axis=-1)
    rig = unrefined_rig("arm", keypoints, skeleton, 30.0)
    weights = kept_skin_weights(points[0, :50], keypoints[0], *skeleton)
    params = sr.initial_params(
        rig.positions, rig.rotations, rig.rest_positions, rig.parents, weights
    )
    order = sr.tree_order(rig.parents)
    positions, world, _ = sr.articulate(params, rig.parents, order)
    np.testing.assert_allclose(positions, rig.positions, atol=2e-5)
    np.testing.assert_allclose(world, rig.rotations, atol=2e-5)
    np.testing.assert_allclose(
        sr.rest_joints(params, rig.parents, order), rig.rest_positions, atol=1e-5
    )
    np.testing.assert_allclose(sr.skin_weights(params), weights, atol=sr.WEIGHT_FLOOR * 20)


def small_case(frames: int = 3, seed: int = 0):
    """Random parameters of a 4-joint tree (root 0; 1 under it; 2 and 3 under 1), a rest surface
    (32, 3) and every frame's points (T, 40, 3): the objective's mechanics, not a fit."""
    rng = np.random.default_rng(seed)
    parents = (0, 0, 1, 1)
    rest = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.3], [0.2, 0.0, 0.5], [-0.2, 0.0, 0.5]])
    axis_angles = rng.normal(scale=0.3, size=(frames, 4, 3))
    world = np.asarray(geometry.axis_angle_to_matrix(jnp.asarray(axis_angles)), np.float64)
    positions = rest + rng.normal(scale=0.02, size=(frames, 4, 3))
    weights = rng.dirichlet(np.ones(4), size=32)
    params = sr.initial_params(positions, world, rest, parents, weights)
    surface = jnp.asarray(rng.uniform(-0.3, 0.6, (32, 3)), jnp.float32)
    targets = jnp.asarray(rng.uniform(-0.3, 0.6, (frames, 40, 3)), jnp.float32)
    return params, surface, targets, parents, sr.tree_order(parents)


def test_the_objective_runs_under_jit_and_vmap_with_finite_gradients():
    params, surface, targets, parents, order = small_case()
    anchor = params["offsets"]

    def total(p, settings=TINY):
        return sr.objective(p, surface, targets, anchor, parents, order, settings)

    value, terms = jax.jit(total)(params)
    # The Chamfer term is the mean over frames of each frame's Chamfer of the skinned surface.
    positions, world, _ = jax.jit(sr.articulate, static_argnums=(1, 2))(params, parents, order)
    rest = sr.rest_joints(params, parents, order)
    skinned = sr.skin(positions, world, rest, sr.skin_weights(params), surface)
    per_frame = [metrics.chamfer_distance(skinned[t], targets[t]) for t in range(len(targets))]
    np.testing.assert_allclose(terms["chamfer"], np.mean(per_frame), rtol=1e-5)
    expected = (
        terms["chamfer"]
        + TINY.smooth_weight * terms["smooth"]
        + TINY.entropy_weight * terms["entropy"]
        + TINY.offset_weight * terms["offset"]
    )
    np.testing.assert_allclose(value, expected, rtol=1e-6)
    assert float(terms["offset"]) == 0.0  # at the start
    grads = jax.jit(jax.grad(lambda p: total(p)[0]))(params)
    for name, grad in grads.items():
        assert grad.shape == params[name].shape and bool(jnp.all(jnp.isfinite(grad))), name
    assert float(jnp.abs(grads["offsets"]).max()) > 0 and float(jnp.abs(grads["logits"]).max()) > 0
    # Fixed weights take no gradient.
    fixed = sr.RefineSettings(fit_weights=False)
    grads = jax.jit(jax.grad(lambda p: total(p, fixed)[0]))(params)
    assert float(jnp.abs(grads["logits"]).max()) == 0.0
    # Several sequences at once: the objective vmaps over a leading axis too.
    stacked = jax.tree.map(lambda x: jnp.stack([x, x]), params)
    both = jax.jit(jax.vmap(lambda p: total(p)[0]))(stacked)
    np.testing.assert_allclose(both, [value, value], rtol=1e-5)


def test_the_fit_is_deterministic():
    points, _, keypoints, skeleton = arm_case(frames=4)
    settings = sr.RefineSettings(iterations=3, surface_points=48, target_points=48)
    first, _ = refine_sequence(keypoints, points, skeleton, 1.0, settings, progress=False)
    again, _ = refine_sequence(keypoints, points, skeleton, 1.0, settings, progress=False)
    for key in ("positions", "rotations", "weights", "rest_positions", "chamfer_history"):
        np.testing.assert_array_equal(first[key], again[key], err_msg=key)


def test_the_priors_are_what_the_docstring_states():
    local = geometry.axis_angle_to_matrix(
        jnp.asarray([[[0.0, 0.0, 0.1 * t]] for t in range(5)], jnp.float32)
    )  # (5, 1, 3, 3): a constant angular velocity w = 0.1 a frame, which costs only O(w^4)
    assert float(sr.rotation_smoothness(local)) < 3 * 0.1**4
    jerk = local.at[2].set(jnp.eye(3) * jnp.asarray([1.0, -1.0, -1.0])[:, None])
    assert float(sr.rotation_smoothness(jerk)) > 0.1
    assert float(sr.rotation_smoothness(local[:2])) == 0.0
    np.testing.assert_allclose(sr.weight_entropy(jnp.zeros((3, 4))), np.log(4), rtol=1e-6)
    assert float(sr.weight_entropy(jnp.asarray([[30.0, 0.0, 0.0]]))) < 1e-6


@pytest.mark.parametrize(
    ("field", "value"),
    [("iterations", 0), ("surface_points", 0), ("learning_rate", 0.0), ("smooth_weight", -1.0)],
)
def test_bad_settings_are_refused_by_name(field, value):
    with pytest.raises(ValueError, match=field):
        sr.RefineSettings(**{field: value})


# --- a phase-1 run ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return make_skel_run(tmp_path_factory.mktemp("refine"))


def test_refine_run_writes_a_refined_skeleton_that_reads_back(tiny, tmp_path):
    run = tmp_path / "skel"
    shutil.copytree(tiny["skel"], run)
    (name,) = run_folder.load_trajectories(run, "test")
    assert run_folder.read_refined(run, "test", name) is None
    seen = []
    (done,) = refine_run(run, settings=TINY, progress=False, report=seen.append)
    assert seen == [done] and done.name == name and done.fit_after < done.fit_before
    assert done.path == run_folder.refined_file(run, "test", name) and done.path.is_file()
    assert run_folder.refined_sequences(run, "test") == [name]
    arrays = run_folder.read_refined(run, "test", name)
    keypoints = run_folder.load_trajectories(run, "test")[name]
    assert arrays["positions"].shape == (len(keypoints), len(PARENTS), 3)
    np.testing.assert_array_equal(arrays["joints"], ORDER)  # all kept, parents first
    assert arrays["settings"]["iterations"] == TINY.iterations
    assert float(arrays["box_scale"]) > 0
    lengths = bone_lengths_over_time(arrays["positions"], arrays["parents"])
    assert np.max(lengths.std(axis=0)) < 1e-6
    # Nothing else of the run changed; no temporary file is left.
    assert not list(done.path.parent.glob(".*"))
    assert run_folder.load_trajectories(run, "test")[name].tobytes() == keypoints.tobytes()


def test_a_damaged_refined_file_is_named_with_the_command_that_rewrites_it(tiny, tmp_path):
    run = tmp_path / "skel"
    shutil.copytree(tiny["skel"], run)
    (name,) = run_folder.load_trajectories(run, "test")
    path = run_folder.refined_file(run, "test", name)
    path.parent.mkdir(parents=True)
    np.savez(path, joints=np.arange(3))
    with pytest.raises(ValueError, match="nmjax refine --run"):
        run_folder.read_refined(run, "test", name)
    with pytest.raises(ValueError, match="holds"):
        run_folder.write_refined(run, "test", name, {"joints": np.arange(3)})


def refused(capsys, *argv) -> str:
    assert nmjax_main(["refine", *map(str, argv)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("nmjax refine"), err
    return err[0]


def test_the_command_refines_one_sequence_and_refuses_bad_inputs(tiny, tmp_path, capsys):
    run = tmp_path / "skel"
    shutil.copytree(tiny["skel"], run)
    (name,) = run_folder.load_trajectories(run, "test")
    argv = ["--run", run, "--seq", name, "--iters", "3", "--no-progress"]
    assert nmjax_main(["refine", *map(str, argv)]) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith(f"nmjax refine: {name}: fit error") and "wrote" in line
    assert run_folder.read_refined(run, "test", name)["settings"]["iterations"] == 3

    assert "does not exist" in refused(capsys, "--run", tmp_path / "missing")
    assert "'nope'" in refused(capsys, "--run", run, "--seq", "nope")
    assert "--iters" in refused(capsys, "--run", run, "--iters", "0")
    assert "export-keypoints" in refused(capsys, "--run", run, "--split", "train")
    assert "invalid choice" in refused(capsys, "--run", run, "--split", "val")
    phase2 = tmp_path / "dyn"
    phase2.mkdir()
    (phase2 / run_folder.CONFIG_FILE).write_text(json.dumps({"skel_run": str(run)}))
    assert "phase-2 run" in refused(capsys, "--run", phase2)
    bare = tmp_path / "bare"
    shutil.copytree(run, bare)
    (bare / run_folder.SKELETON_FILE).unlink()
    assert "extract-skeleton" in refused(capsys, "--run", bare)


# --- the benchmark script, on a tiny run --------------------------------------------------------


def test_the_benchmark_script_compares_refined_and_unrefined_on_a_tiny_run(tiny, tmp_path):
    bench = load_experiment("refine_bench.py")
    run = tmp_path / "skel"
    shutil.copytree(tiny["skel"], run)
    out = tmp_path / "results"
    bench.main(
        [
            "--run",
            str(run),
            "--iters",
            "3",
            "--surface-points",
            "48",
            "--target-points",
            "48",
            "--timing-frames",  # the tiny sequence's own shape: its compiled step serves both
            "12",
            "--timing-points",
            "1500",
            "--out",
            str(out),
            "--allow-dirty",
        ]
    )
    stored = json.loads((out / "refine_synth-arm.json").read_text())
    (row,) = stored["rows"]
    assert row["run"] == str(run) and row["seed"] == 0
    for method in ("unrefined", "refined"):
        scores = row["scores"][method]
        for key in bench.SCORE_KEYS:
            assert key in scores, (method, key)
    assert row["scores"]["refined"]["bone_length_variation"] < 1e-6
    assert (
        row["scores"]["refined"]["tree_edit_distance"]
        == row["scores"]["unrefined"]["tree_edit_distance"]
    )
    assert row["timing"]["frames"] == 12 and row["timing"]["points"] == 1500
    assert row["targets"]["timing_seconds"]["met"] is None  # not the 60 x 8,000 sequence
    assert set(row["targets"]) == set(bench.TARGETS)
    markdown = (out / "refine_synth-arm.md").read_text()
    assert "| joint_distance |" in markdown and "Provenance" in markdown
    assert provenance.read_png(out / "refine_synth-arm.png") is not None
