"""Tests of nmjax.tasks (generation, interpolation, baselines, retargeting) and its commands."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx
from tiny_runs import PARENTS, make_runs

from nmjax import geometry, tasks
from nmjax.config import DynamicsConfig
from nmjax.config_io import replace_fields
from nmjax.data import meshes
from nmjax.models.dynamics import Dynamics, bone_lengths
from nmjax.skeleton import skeleton_from_parents, skin_weights

K = len(PARENTS)
SKELETON = skeleton_from_parents(np.array(PARENTS))
TINY = DynamicsConfig(latent=4, hidden=16, mlp=16, posterior_samples=3)


def random_rotations(rng: np.random.Generator, shape: tuple[int, ...], scale: float = 1.0):
    axis_angle = rng.normal(size=(*shape, 3)) * scale
    return np.asarray(geometry.axis_angle_to_matrix(jnp.asarray(axis_angle)), np.float64)


def numpy_fk(root, local, offsets, parents, order):
    """Eq. 2 one joint at a time: (T,3), (T,K,3,3), (K,3) -> positions (T,K,3), globals."""
    t = len(root)
    pos, glob = np.zeros((t, K, 3)), np.zeros((t, K, 3, 3))
    for k in order:
        p = parents[k]
        if p == k:
            glob[:, k], pos[:, k] = local[:, k], root
        else:
            glob[:, k] = glob[:, p] @ local[:, k]
            pos[:, k] = pos[:, p] + np.einsum("tij,j->ti", glob[:, k], offsets[k])
    return pos, glob


@pytest.fixture(scope="module")
def model():
    return Dynamics(TINY, SKELETON.parents, SKELETON.order, rngs=nnx.Rngs(0))


def jitted(model, fn):
    """fn(model, *args) compiled once (the model split outside, merged inside)."""
    graphdef, state = nnx.split(model)

    @jax.jit
    def call(state, *args):
        return fn(nnx.merge(graphdef, state), *args)

    return lambda *args: call(state, *args)


def keyframes(seed: int, batch: int = 2):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-0.5, 0.5, (batch, K, 4)).astype(np.float32)
    x[..., 3] = rng.uniform(0.3, 1.0, (batch, K))
    return jnp.asarray(x)


# --- interpolation ---------------------------------------------------------------------------


def test_lerp_between_identical_keyframes_is_constant():
    x = keyframes(0)
    out = np.asarray(tasks.lerp_keypoints(x, x, 7))
    assert out.shape == (2, 8, K, 4)
    np.testing.assert_allclose(out, np.broadcast_to(np.asarray(x)[:, None], out.shape), atol=1e-7)


def test_lerp_is_linear_in_time():
    a, b = keyframes(1), keyframes(2)
    out = np.asarray(tasks.lerp_keypoints(a, b, 4))
    for i in range(5):
        np.testing.assert_allclose(out[:, i], (1 - i / 4) * a + (i / 4) * b, atol=1e-6)


def test_slerp_between_identical_keyframes_is_constant_inside(model):
    x = keyframes(3)
    out = np.asarray(tasks.slerp_jit(*nnx.split(model), x, x, jax.random.key(0), gap=5))
    assert out.shape == (2, 6, K, 4)
    np.testing.assert_array_equal(out[:, 0], x)
    np.testing.assert_array_equal(out[:, -1], x)
    # every in-between frame is the FK of the same rotations: one pose repeated
    np.testing.assert_allclose(
        out[:, 1:-1], np.broadcast_to(out[:, 1:2], out[:, 1:-1].shape), atol=1e-6
    )


def test_slerp_midpoint_uses_the_geodesic_between_the_inferred_rotations(model):
    a, b = keyframes(4), keyframes(5)
    key = jax.random.key(1)
    out = np.asarray(tasks.slerp_jit(*nnx.split(model), a, b, key, gap=2))
    lengths_ab = bone_lengths(jnp.stack([a, b], axis=1), PARENTS)
    infer = jitted(model, lambda m, x, k, lengths: m(x, k, lengths=lengths))
    rot = np.stack(
        [np.asarray(infer(x[:, None], key, lengths_ab).rotations[:, 0]) for x in (a, b)],
        axis=1,
    ).astype(np.float64)  # each keyframe inferred on its own
    # independent midpoint: R_mid = R0 expm(0.5 log(R0^T R1)) via scipy
    from scipy.spatial.transform import Rotation

    rel = Rotation.from_matrix((np.swapaxes(rot[:, 0], -1, -2) @ rot[:, 1]).reshape(-1, 3, 3))
    half = Rotation.from_rotvec(0.5 * rel.as_rotvec()).as_matrix().reshape(2, K, 3, 3)
    mid = rot[:, 0] @ half
    lengths = np.linalg.norm(
        np.asarray(jnp.stack([a, b], 1))[..., :3]
        - np.asarray(jnp.stack([a, b], 1))[:, :, list(PARENTS), :3],
        axis=-1,
    )
    lower_median = np.min(lengths, axis=1)  # torch's median of two frames: the lower value
    offsets = np.asarray(model.directions[...])[None] * lower_median[..., None]
    root = SKELETON.root
    for i in range(2):
        centre = 0.5 * (np.asarray(a)[i, root, :3] + np.asarray(b)[i, root, :3])
        expect, _ = numpy_fk(centre[None], mid[i][None], offsets[i], PARENTS, SKELETON.order)
        np.testing.assert_allclose(out[i, 1, :, :3], expect[0], atol=2e-4)
    np.testing.assert_allclose(out[:, 1, :, 3], 0.5 * (a[..., 3] + b[..., 3]), atol=1e-6)


def test_interpolation_keeps_the_rollout_ending_closest_to_the_end_keyframe(model):
    a, b = keyframes(6), keyframes(7)
    key, n, gap = jax.random.key(2), 5, 4
    out = np.asarray(
        tasks.interpolate_jit(*nnx.split(model), a[:, None], b, key, gap=gap, num_trajectories=n)
    )
    assert out.shape == (2, gap + 1, K, 4)
    np.testing.assert_array_equal(out[:, 0], a)
    np.testing.assert_array_equal(out[:, -1], b)
    generate = jitted(model, lambda m, x, k: m.generate(x, gap, k))
    rollouts = np.stack(
        [np.asarray(generate(a[:, None], k)[0])[:, 1:] for k in jax.random.split(key, n)]
    )  # (N, B, gap, K, 4), each trajectory on its own
    err = np.sum((rollouts[:, :, -1, :, :3] - np.asarray(b)[None, :, :, :3]) ** 2, axis=(-2, -1))
    for i in range(2):
        best = rollouts[np.argmin(err[:, i]), i]
        np.testing.assert_allclose(out[i, 1:-1], best[:-1], atol=1e-5)


def test_generation_keeps_the_observed_frames_and_draws_independent_samples_per_key(model):
    x = jnp.stack([keyframes(8), keyframes(9), keyframes(10)], axis=1)  # (2, 3, K, 4)
    key = jax.random.key(3)
    kp, rot = tasks.generate_jit(*nnx.split(model), x, key, num_frames=4, num_samples=3)
    assert kp.shape == (2, 3, 7, K, 4) and rot.shape == (2, 3, 7, K, 3, 3)
    generate = jitted(model, lambda m, x, k: m.generate(x, 4, k))
    for s, k in enumerate(jax.random.split(key, 3)):
        # The conditioning frames are the observed ones, not the posterior's reconstruction of
        # them (the untrained model's is far off); the rest is the model's own sample s.
        np.testing.assert_array_equal(np.asarray(kp[:, s, :3]), np.asarray(x))
        one, one_rot = generate(x, k)
        assert not np.allclose(np.asarray(one[:, :3]), np.asarray(x), atol=1e-3)
        np.testing.assert_allclose(np.asarray(kp[:, s, 3:]), np.asarray(one[:, 3:]), atol=1e-5)
        np.testing.assert_allclose(np.asarray(rot[:, s]), np.asarray(one_rot), atol=1e-5)
    assert not np.allclose(kp[:, 0, -1], kp[:, 1, -1])

    # bone lengths measured on the conditioning frames (Eq. 20) are kept exactly by the FK decoder
    def lengths(y):
        return np.linalg.norm(y[..., :3] - y[..., list(PARENTS), :3], axis=-1)

    np.testing.assert_allclose(
        lengths(np.asarray(kp[:, 0, -1])), np.asarray(bone_lengths(x, PARENTS)), atol=1e-4
    )


def test_generation_callers_infer_the_observed_frames_with_the_configured_samples(monkeypatch):
    """Every caller of `generate` draws the config's S = 10 posterior samples per observed frame
    (the release's best-of-10); samples=1 is still there for a caller that asks for it."""
    from nmjax import evaluate
    from nmjax.train import dyn

    # Sizes no other test uses, so the compiled callers below are traced (and spied on) afresh.
    model = Dynamics(
        DynamicsConfig(latent=3, hidden=7, mlp=5),
        SKELETON.parents,
        SKELETON.order,
        rngs=nnx.Rngs(0),
    )
    assert model.samples == 10
    drawn, generating = [], []
    posterior_step, generate = Dynamics.posterior_step, Dynamics.generate

    def spy_posterior(self, h, x, lengths, key, samples):
        if generating:
            drawn.append(samples)
        return posterior_step(self, h, x, lengths, key, samples)

    def spy_generate(self, *args, **kwargs):
        generating.append(True)
        try:
            return generate(self, *args, **kwargs)
        finally:
            generating.pop()

    monkeypatch.setattr(Dynamics, "posterior_step", spy_posterior)
    monkeypatch.setattr(Dynamics, "generate", spy_generate)
    x = jnp.stack([keyframes(8), keyframes(9)], axis=1)  # (B=2, T_cond=2, K, 4)
    key = jax.random.key(0)
    callers = {
        "generate_motion": lambda: tasks.generate_motion(model, x, 3, key, num_samples=2),
        "interpolate_motion": lambda: tasks.interpolate_motion(model, x, x[:, -1], 3, key, 2),
        "evaluate.generated_futures": lambda: evaluate.generated_futures(
            nnx.split(model), np.asarray(x), 3, 2, key
        ),
        "dyn.evaluate": lambda: dyn.evaluate(model, jnp.concatenate([x, x], axis=1), x, key),
    }
    for name, call in callers.items():
        drawn.clear()
        call()
        assert drawn and set(drawn) == {10}, name
    drawn.clear()
    tasks.generate_motion(model, x, 3, key, num_samples=2, posterior_samples=1)
    assert drawn and set(drawn) == {1}


# --- retargeting -----------------------------------------------------------------------------


def test_align_rotation_maps_u_onto_v_including_antiparallel():
    rng = np.random.default_rng(0)
    u = rng.normal(size=(6, 3))
    v = rng.normal(size=(6, 3))
    v[0] = -u[0]  # antiparallel
    v[1] = 2 * u[1]  # parallel
    r = np.asarray(geometry.align_rotation(jnp.asarray(u), jnp.asarray(v)), np.float64)
    unit = lambda x: x / np.linalg.norm(x, axis=-1, keepdims=True)  # noqa: E731
    np.testing.assert_allclose(np.einsum("kij,kj->ki", r, unit(u)), unit(v), atol=1e-5)
    np.testing.assert_allclose(
        r @ np.swapaxes(r, -1, -2), np.broadcast_to(np.eye(3), r.shape), atol=1e-5
    )
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-5)
    np.testing.assert_allclose(r[1], np.eye(3), atol=1e-5)


def source_motion(seed: int = 0, frames: int = 5):
    """A known skeletal motion: directions, offsets, rotations, root path and positions."""
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(K, 3))
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    offsets = directions * rng.uniform(0.2, 0.4, (K, 1))
    local = random_rotations(rng, (frames, K), 0.5)
    root = rng.normal(size=(frames, 3)) * 0.1
    pos, glob = numpy_fk(root, local, offsets, PARENTS, SKELETON.order)
    return directions, local, root, pos, glob


def test_retargeting_onto_its_own_skeleton_reproduces_the_source_motion():
    directions, local, root, pos, glob = source_motion()
    joints, rotations = tasks.retarget_joints(
        jnp.asarray(root), jnp.asarray(local), jnp.asarray(directions), jnp.asarray(pos[0]),
        SKELETON.parents, SKELETON.order,
    )  # fmt: skip
    np.testing.assert_allclose(np.asarray(joints), pos, atol=1e-5)
    np.testing.assert_allclose(np.asarray(rotations), glob, atol=1e-5)


def test_retargeting_changes_bone_lengths_not_rotations():
    directions, local, root, pos, _ = source_motion(1)
    target = pos[0] * 1.5  # same pose, every bone 1.5 times longer
    joints, _ = tasks.retarget_joints(
        jnp.asarray(root), jnp.asarray(local), jnp.asarray(directions), jnp.asarray(target),
        SKELETON.parents, SKELETON.order,
    )  # fmt: skip
    bones = lambda x: x - x[..., list(PARENTS), :]  # noqa: E731
    np.testing.assert_allclose(bones(np.asarray(joints)), 1.5 * bones(pos), atol=1e-5)


def limb_mesh_points(pos0: np.ndarray, rng: np.random.Generator, per_bone: int = 40):
    """Points around every bone of a pose (a crude mesh surface)."""
    pts = []
    for k, p in enumerate(PARENTS):
        if p == k:
            continue
        s = rng.uniform(0.05, 0.95, (per_bone, 1))
        pts.append(pos0[p] + s * (pos0[k] - pos0[p]) + rng.normal(size=(per_bone, 3)) * 0.01)
    return np.concatenate(pts)


def test_mesh_retargeted_onto_itself_follows_the_source_motion():
    directions, local, root, pos, glob = source_motion(2)
    vertices = limb_mesh_points(pos[0], np.random.default_rng(0))
    weights = skin_weights(vertices, pos[0], SKELETON)
    rest = tasks.rest_rotations(
        jnp.asarray(pos[0]), jnp.asarray(glob[0]), jnp.asarray(directions), SKELETON.parents
    )
    np.testing.assert_allclose(np.asarray(rest), glob[0], atol=1e-5)  # already consistent
    joints, rotations = tasks.retarget_joints(
        jnp.asarray(root), jnp.asarray(local), jnp.asarray(directions), jnp.asarray(pos[0]),
        SKELETON.parents, SKELETON.order,
    )  # fmt: skip
    moved = np.asarray(
        tasks.retarget_vertices(
            jnp.asarray(vertices),
            jnp.asarray(weights),
            jnp.asarray(pos[0]),
            rest,
            joints,
            rotations,
        )  # fmt: skip
    )
    # independent LBS: each joint's rigid motion from the true globals, blended by the weights
    rel = glob @ np.swapaxes(glob[:1], -1, -2)  # (T, K, 3, 3)
    per_joint = np.einsum("tkij,vkj->tvki", rel, vertices[:, None] - pos[0][None]) + pos[:, None]
    expect = np.einsum("vk,tvki->tvi", weights, per_joint)
    np.testing.assert_allclose(moved, expect, atol=1e-4)
    np.testing.assert_allclose(moved[0], vertices, atol=1e-5)  # frame 0 is the rest pose


def test_retargeted_mesh_starts_as_the_given_mesh_when_the_source_starts_in_its_pose():
    """`retarget_mesh` (what `nmjax retarget` writes): frame 0 is the input mesh itself when the
    source's first pose is the target's; here the target is the source's first pose with every
    bone 1.5 times longer, elsewhere in space, its inferred rotations the source's first ones."""
    directions, local, root, pos, _ = source_motion(4, frames=4)
    target = np.array([0.3, -0.2, 0.1]) + root[0] + 1.5 * (pos[0] - root[0])
    vertices = limb_mesh_points(target, np.random.default_rng(5))
    weights = skin_weights(vertices, target, SKELETON)
    moved, joints = tasks.retarget_mesh(
        jnp.asarray(vertices, jnp.float32), jnp.asarray(weights), jnp.asarray(target),
        jnp.asarray(local[0]), jnp.asarray(local), jnp.asarray(root), jnp.asarray(directions),
        SKELETON.parents, SKELETON.order,
    )  # fmt: skip
    moved, joints = np.asarray(moved), np.asarray(joints)
    np.testing.assert_allclose(moved[0], vertices, atol=1e-5)
    np.testing.assert_allclose(joints[0], target, atol=1e-5)
    # ... and then it moves with the source: the root by the source root's displacement.
    assert np.abs(moved[1:] - vertices).max() > 0.01
    r = SKELETON.root
    np.testing.assert_allclose(joints[:, r], target[r] + root - root[0], atol=1e-5)


def test_rest_rotations_turn_an_estimate_onto_the_bones():
    directions, _, _, pos, glob = source_motion(3)
    wrong = random_rotations(np.random.default_rng(1), (K,), 1.0)
    rest = np.asarray(
        tasks.rest_rotations(
            jnp.asarray(pos[0]), jnp.asarray(wrong), jnp.asarray(directions), SKELETON.parents
        )
    )
    bones = pos[0] - pos[0][list(PARENTS)]
    for k, p in enumerate(PARENTS):
        if p != k:
            turned = rest[k] @ directions[k]
            np.testing.assert_allclose(turned, bones[k] / np.linalg.norm(bones[k]), atol=1e-5)
    np.testing.assert_allclose(rest[SKELETON.root], wrong[SKELETON.root], atol=1e-6)


# --- meshes ----------------------------------------------------------------------------------


def test_bad_meshes_give_errors_that_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.obj"):
        meshes.load_mesh(tmp_path / "nope.obj")
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing\n")
    with pytest.raises(ValueError, match="empty.obj"):
        meshes.load_mesh(empty)
    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match=r"nan.obj has 1 vertices with NaN"):
        meshes.load_mesh(nan)
    cloud = tmp_path / "cloud.obj"
    cloud.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(ValueError, match="cloud.obj has no"):
        meshes.load_mesh(cloud)
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 9\x00\xff")
    with pytest.raises(ValueError, match="garbage.ply"):
        meshes.load_mesh(garbage)
    good = tmp_path / "tri.obj"
    good.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    assert len(meshes.load_mesh(good).faces) == 1


# --- the commands on a tiny run ---------------------------------------------------------------


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return make_runs(tmp_path_factory.mktemp("tiny"))


def test_phase2_trains_on_crops_of_the_phase1_run(runs):
    """The default inputs: the detector of the phase-1 run on every crop of its training split,
    made for the trainer (whose loop the "sequence" tests cover) once the run is accepted."""
    from nmjax.config import dyn_preset
    from nmjax.train import dyn_inputs

    cfg = dyn_preset("synth-arm", "tiny")
    assert cfg.data.inputs == "crop"
    frames = cfg.data.frames
    count, inputs = dyn_inputs.phase2_inputs(cfg, runs["skel"], K)
    data = inputs()  # the validation clips are detected now, training crops later
    detector = dyn_inputs.phase2_detector(runs["skel"])
    train_seqs = list(dyn_inputs.split_sequences(detector, "train").values())
    assert count == len(train_seqs)
    starts = [dyn_inputs.crop_starts(seq.num_frames, frames, 1) for seq in train_seqs]
    crops = data.crops
    assert crops.num_starts == sum(len(s) for s in starts) > len(train_seqs)
    assert crops.detected == 0 and crops.num_keypoints == K
    last = (train_seqs[-1], int(starts[-1][-1]))  # the last crop of the table
    batch = crops.batch(np.array([crops.num_starts - 1, 0, crops.num_starts - 1]))
    assert batch.shape == (3, frames, K, 4) and crops.detected == 2  # each detected once
    assert crops.postfix() == {"crops_detected": f"2/{crops.num_starts}"}
    np.testing.assert_allclose(
        batch[0], dyn_inputs.detect_clips(detector, [last], frames)[0], atol=1e-6
    )
    np.testing.assert_array_equal(batch[0], batch[2])
    assert data.val.shape[1:] == (frames, K, 4) and data.val_cond.shape[1] == 1


def test_crops_are_detected_when_first_drawn_and_a_resumed_run_sees_the_same_batches(
    runs, tmp_path, monkeypatch
):
    """No detector pass before the first step; at most min(starts, crops drawn) crops detected;
    a run stopped after 2 steps and resumed (its crops detected again) logs the losses of an
    uninterrupted one."""
    import dataclasses

    from nmjax.config import dyn_preset
    from nmjax.train import dyn, dyn_inputs, metric_log

    made = []
    crop_inputs = dyn_inputs.crop_inputs

    def recording(*args, **kwargs):
        made.append(crop_inputs(*args, **kwargs))
        return made[-1]

    monkeypatch.setattr(dyn_inputs, "crop_inputs", recording)
    before_first_step = []

    def hook(step, state):
        if step == 0:
            before_first_step.append(made[-1].crops.detected)
        return state

    cfg = replace_fields(
        dyn_preset("synth-arm", "tiny"),
        skel_run=str(runs["skel"]),
        steps=4,
        log_every=1,
        val_every=4,
        ckpt_every=2,
    )

    def losses(run):
        return [r["train/loss"] for r in metric_log.read_metrics(run) if "train/loss" in r]

    straight = dataclasses.replace(cfg, run=str(tmp_path / "straight"))
    dyn.train_dynamics(straight, progress=False, step_hook=hook)
    crops = made[-1].crops
    assert before_first_step == [0]
    assert 0 < crops.detected <= min(crops.num_starts, cfg.loop.steps * cfg.data.batch_size)

    stopped = replace_fields(cfg, run=str(tmp_path / "stopped"), steps=2)
    dyn.train_dynamics(stopped, progress=False)
    resumed = replace_fields(stopped, steps=4)
    dyn.train_dynamics(resumed, resume=True, progress=False)
    assert made[-1].crops.detected <= 2 * cfg.data.batch_size  # only the last two steps' draws
    np.testing.assert_allclose(
        losses(tmp_path / "stopped"), losses(tmp_path / "straight"), rtol=1e-6
    )


def test_generate_command(runs, tmp_path):
    from nmjax import cli

    out = tmp_path / "gen"
    # 2 + 11 frames: longer than the 12-frame test sequence, whose last frame is then held.
    argv = ["generate", "--run", str(runs["nm"]), "--cond", "2", "--gen", "11", "--samples", "2"]
    assert cli.main([*argv, "--inputs", "1", "--voxels", "--out", str(out)]) == 0
    with np.load(out / "generate.npz") as z:
        assert z["keypoints"].shape == (1, 2, 13, K, 4)
        assert np.all(np.isfinite(z["keypoints"]))
        assert z["observed"].shape == (1, 13, K, 4) and list(z["observed_frames"]) == [12]
        np.testing.assert_array_equal(z["observed"][0, 12], z["observed"][0, 11])
        for s in range(2):  # every sample starts with the 2 observed frames it was given
            np.testing.assert_array_equal(z["keypoints"][:, s, :2], z["observed"][:, :2])
        name = str(z["names"][0])
        observed = z["observed"]
    # "crop" inputs: the clip's first crop (T = 6 frames) normalised on its own, its first 2
    # frames through the detector on their own, as the release's generation conditions.
    from nmjax.train import dyn_inputs

    detector = dyn_inputs.phase2_detector(runs["skel"])
    seq = dyn_inputs.split_sequences(detector, "test")[name]
    x_cond = dyn_inputs.detect_clips(detector, [(seq, 0)], 6, detect=2)
    np.testing.assert_allclose(observed[:, :2], x_cond, atol=1e-6)
    with np.load(out / "voxels.npz") as z:
        assert z["voxels"].shape == (1, 2, 13, 16, 16, 16)
    assert (out / f"{name}.gif").stat().st_size > 0 and (out / f"{name}.png").is_file()


def test_interpolate_command(runs, tmp_path):
    from nmjax import cli

    out = tmp_path / "interp"
    argv = ["interpolate", "--run", str(runs["nm"]), "--gap", "3", "--trajectories", "2"]
    assert (
        cli.main([*argv, "--inputs", "1", "--vrnn-run", str(runs["vrnn"]), "--out", str(out)]) == 0
    )
    with np.load(out / "interpolate.npz") as z:
        for method in ("Ours", "VRNN", "Lerp", "Slerp"):
            assert z[method].shape == (1, 4, K, 4)
            np.testing.assert_array_equal(z[method][:, 0], z["truth"][:, 0])
            np.testing.assert_array_equal(z[method][:, -1], z["truth"][:, -1])


def test_interpolate_command_takes_a_point_sequence_file(runs, tmp_path):
    """`interpolate --source-file`: the keyframes and truth are the file's first gap + 1 frames
    (every --source-rate-th) detected as one crop, the output named after the file."""
    from nmjax import cli
    from nmjax.data.datasets import load_sequences

    (seq,) = load_sequences("synth-arm", "test", runs["data"])[:1]
    motion = tmp_path / "motion.npy"
    np.save(motion, np.asarray(seq.vertices, np.float32))
    out = tmp_path / "interp"
    argv = ["interpolate", "--run", str(runs["nm"]), "--gap", "3", "--trajectories", "2"]
    argv += ["--source-file", str(motion), "--source-rate", "2", "--out", str(out)]
    assert cli.main([*argv, "--vrnn-run", str(runs["vrnn"])]) == 0
    _, truth, _ = tasks.source_file_clip(runs["skel"], motion, 4, 2)
    with np.load(out / "interpolate.npz") as z:
        assert list(z["names"]) == ["motion"]
        np.testing.assert_allclose(z["truth"], truth, atol=1e-6)
        for method in ("Ours", "VRNN", "Lerp", "Slerp"):
            assert z[method].shape == (1, 4, K, 4) and np.all(np.isfinite(z[method]))
            np.testing.assert_array_equal(z[method][:, 0], z["truth"][:, 0])
            np.testing.assert_array_equal(z[method][:, -1], z["truth"][:, -1])
    assert (out / "motion.gif").stat().st_size > 0


def test_retarget_command_and_bad_mesh(runs, tmp_path, capsys):
    import trimesh

    from nmjax import cli

    target = tmp_path / "box.obj"
    box = trimesh.creation.box(extents=(0.2, 0.3, 1.0))
    box.export(target)
    out = tmp_path / "re"
    argv = ["retarget", "--run", str(runs["nm"]), "--target", str(target), "--frames", "3"]
    assert cli.main([*argv, "--points", "800", "--out", str(out)]) == 0
    frames = sorted(out.glob("frame_*.obj"))
    assert len(frames) == 3
    mesh = trimesh.load(frames[0], force="mesh", process=False)
    assert mesh.vertices.shape == (8, 3) and np.all(np.isfinite(mesh.vertices))
    np.testing.assert_array_equal(mesh.faces, box.faces)  # the target's own triangles
    assert (out / "retarget.gif").is_file()
    bad = tmp_path / "bad.obj"
    bad.write_text("v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    argv = ["retarget", "--run", str(runs["nm"]), "--target", str(bad), "--out", str(out)]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "bad.obj" in err and len(err.strip().splitlines()) == 1


def test_retarget_takes_every_source_frame_by_default(runs, tmp_path):
    import trimesh

    from nmjax import cli, run_folder

    target = tmp_path / "box.obj"
    trimesh.creation.box(extents=(0.2, 0.3, 1.0)).export(target)
    out = tmp_path / "re"
    argv = ["retarget", "--run", str(runs["nm"]), "--target", str(target), "--points", "800"]
    assert cli.main([*argv, "--out", str(out)]) == 0
    trajectories = run_folder.load_trajectories(runs["skel"], "test")
    assert len(trajectories[min(trajectories)]) == 12  # the first test sequence, all its frames
    assert len(sorted(out.glob("frame_*.obj"))) == 12


def test_retarget_names_a_phase1_run_and_a_point_cloud_target(runs, tmp_path, capsys):
    import trimesh

    from nmjax import cli

    target = tmp_path / "box.obj"
    trimesh.creation.box().export(target)

    def refused(run, mesh) -> str:
        assert cli.main(["retarget", "--run", str(run), "--target", str(mesh)]) == 2
        (line,) = capsys.readouterr().err.strip().splitlines()
        return line

    line = refused(runs["skel"], target)
    assert "phase-1 run" in line and "phase-2 run" in line and "train-dyn" in line
    assert "`nmjax rig --from RAW` makes a rig in one command" in line
    assert not (runs["skel"] / "retarget-box").exists()
    cloud = tmp_path / "cloud.ply"
    trimesh.PointCloud(np.random.default_rng(0).normal(size=(50, 3))).export(cloud)
    line = refused(runs["nm"], cloud)
    assert "cloud.ply" in line and "point cloud (50 points)" in line and "with faces" in line
    assert "has no vertices" not in line


def test_retarget_help_shows_the_defaults(capsys):
    from nmjax import cli

    assert cli.main(["retarget", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    for default in (
        "(default: every frame of the source)",
        "(default: 20000)",
        "(default: 0)",
        "(default: the first by name)",
        "(default: RUN/retarget-TARGET",
    ):
        assert default in text
