"""Tests of `nmjax export` (nmjax.export): glTF and BVH files of the tiny runs, read back by
pygltflib and bvhio and evaluated here by the formats' own rules (written in this file on
purpose, not taken from nmjax), the Khronos validator, the viewer, and every refused input."""

from __future__ import annotations

import base64

import numpy as np
import pygltflib
import pytest
from gltf_validator import validate
from tiny_runs import PARENTS, make_runs

from nmjax import cli, tasks
from nmjax.export import rig as rigmath

K = len(PARENTS)
FK_TOLERANCE = 1e-5  # joint positions, relative to the body's size
SKIN_TOLERANCE = 1e-4  # skinned vertices, relative to the mesh's size


# --- glTF by the specification's rules ----------------------------------------------------------


def load_gltf(path):
    """(document, binary buffer) of a .glb or a .gltf with an embedded buffer."""
    if path.suffix == ".glb":
        doc = pygltflib.GLTF2.load_binary(path)
        return doc, doc.binary_blob()
    doc = pygltflib.GLTF2.load_json(path)
    uri = doc.buffers[0].uri
    assert uri.startswith("data:application/octet-stream;base64,")
    return doc, base64.b64decode(uri.split(",", 1)[1])


def accessor(doc, blob, index):
    """Accessor `index` as (count, components) float64, honouring offsets and strides."""
    acc = doc.accessors[index]
    view = doc.bufferViews[acc.bufferView]
    dtype = {5126: "<f4", 5125: "<u4", 5123: "<u2", 5121: "u1"}[acc.componentType]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[acc.type]
    item = np.dtype(dtype).itemsize * width
    stride = view.byteStride or item
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    rows = [
        np.frombuffer(blob, dtype, width, start + i * stride).astype(np.float64)
        for i in range(acc.count)
    ]
    return np.array(rows)


def quaternion_matrix(q):
    """Rotation matrix of a unit quaternion in glTF's order (x, y, z, w)."""
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def trs(translation, rotation):
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = quaternion_matrix(rotation), translation
    return m


def world_matrices(doc, blob):
    """{node: (T, 4, 4)} world matrices at every key of the first animation: each node's TRS
    (its animated values at the key, else its own), composed from the scene's roots down."""
    animation = doc.animations[0]
    times = accessor(doc, blob, animation.samplers[0].input)[:, 0]
    local = {}
    for n, node in enumerate(doc.nodes):
        if node.mesh is not None:
            continue
        t = np.tile(node.translation or [0.0, 0.0, 0.0], (len(times), 1)).astype(float)
        r = np.tile(node.rotation or [0.0, 0.0, 0.0, 1.0], (len(times), 1)).astype(float)
        local[n] = {"translation": t, "rotation": r}
    for channel in animation.channels:
        sampler = animation.samplers[channel.sampler]
        assert sampler.interpolation == "LINEAR"
        np.testing.assert_array_equal(accessor(doc, blob, sampler.input)[:, 0], times)
        local[channel.target.node][channel.target.path] = accessor(doc, blob, sampler.output)
    world = {}

    def visit(n, parent):
        own = np.stack([trs(t, r) for t, r in zip(*local[n].values(), strict=True)])
        world[n] = own if parent is None else parent @ own
        for child in doc.nodes[n].children or []:
            visit(child, world[n])

    for root in doc.scenes[doc.scene].nodes:
        if doc.nodes[root].mesh is None:
            visit(root, None)
    return times, world


def joint_positions(doc, blob):
    """(times, {joint name: (T, 3)} world positions of the skin's joints)."""
    times, world = world_matrices(doc, blob)
    return times, {doc.nodes[n].name: world[n][:, :3, 3] for n in doc.skins[0].joints}


def node_parents(doc):
    """{node name: parent node name} over the skin's joints (the root maps to itself)."""
    parent = {}
    for node in doc.nodes:
        for child in node.children or []:
            parent[doc.nodes[child].name] = node.name
    names = [doc.nodes[n].name for n in doc.skins[0].joints]
    return {name: parent.get(name, name) for name in names}


def skinned_vertices(doc, blob):
    """(T, V, 3): sum over the four influences of weight x joint matrix x inverse bind matrix x
    vertex, the skinning equation of the glTF specification."""
    _, world = world_matrices(doc, blob)
    skin = doc.skins[0]
    ibm = accessor(doc, blob, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
    joint_matrix = np.stack([world[n] for n in skin.joints], axis=1) @ ibm  # (T, J, 4, 4)
    mesh_node = next(n for n in doc.nodes if n.mesh is not None)
    attributes = doc.meshes[mesh_node.mesh].primitives[0].attributes
    vertices = accessor(doc, blob, attributes.POSITION)
    joints = accessor(doc, blob, attributes.JOINTS_0).astype(int)
    weights = accessor(doc, blob, attributes.WEIGHTS_0)
    homogeneous = np.concatenate([vertices, np.ones((len(vertices), 1))], axis=1)
    out = np.zeros((len(joint_matrix), len(vertices), 3))
    for i in range(4):
        moved = np.einsum("tvij,vj->tvi", joint_matrix[:, joints[:, i]], homogeneous)[..., :3]
        out += weights[:, i, None] * moved
    return out, weights


def in_file_axes(x, up_axis=2):
    """Data coordinates (..., 3) in the file's axes (+Y up)."""
    return np.asarray(x, np.float64) @ rigmath.file_axes(up_axis).T


def size_of(x):
    return float(np.max(np.ptp(np.asarray(x).reshape(-1, 3), axis=0)))


def assert_no_validator_errors(path):
    report = validate(path)
    errors = [m for m in report["issues"]["messages"] if m["severity"] == 0]
    assert report["issues"]["numErrors"] == 0, errors


def export(*argv):
    return cli.main(["export", *map(str, argv)])


# --- fixtures: the untrained tiny runs, a retarget output ---------------------------------------


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return make_runs(tmp_path_factory.mktemp("tiny"))


@pytest.fixture(scope="module")
def retarget(runs, tmp_path_factory):
    """An `nmjax retarget` output of the tiny phase-2 run onto a box (as test_tasks makes it)."""
    import trimesh

    root = tmp_path_factory.mktemp("retarget")
    target = root / "box.obj"
    trimesh.creation.box(extents=(0.2, 0.3, 1.0)).export(target)
    out = root / "re"
    argv = ["retarget", "--run", runs["nm"], "--target", target, "--frames", "3"]
    assert cli.main([*map(str, argv), "--points", "800", "--out", str(out)]) == 0
    return out


# --- the math -------------------------------------------------------------------------------------


def test_euler_zxy_inverts_its_matrix_including_gimbal_lock():
    rng = np.random.default_rng(0)
    angles = rng.uniform(-179, 179, (50, 3))
    angles[:, 1] = rng.uniform(-89, 89, 50)
    angles[:3, 1] = [90.0, -90.0, 89.9999999]  # x at the poles
    rot = rigmath.matrix_from_euler_zxy(angles)
    back = rigmath.matrix_from_euler_zxy(rigmath.euler_zxy(rot))
    np.testing.assert_allclose(back, rot, atol=1e-9)
    # R = Rz Rx Ry: a pure z turn is the first angle, a pure y turn the last.
    np.testing.assert_allclose(
        rigmath.euler_zxy(rigmath.matrix_from_euler_zxy([30.0, 0.0, 0.0])), [30, 0, 0], atol=1e-9
    )
    turn_y = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # +90 about y
    np.testing.assert_allclose(rigmath.euler_zxy(turn_y), [0, 0, 90], atol=1e-9)


def test_swing_rotation_turns_the_rest_bone_onto_the_bone_without_twist():
    rng = np.random.default_rng(1)
    rest = rng.normal(size=(K, 3))
    positions = rng.normal(size=(4, K, 3))
    positions[1, 3] = positions[1, 2] - (rest[3] - rest[2])  # the bone turned by pi
    parents = np.array(PARENTS)
    rot = rigmath.swing_rotations(positions, rest, parents)
    np.testing.assert_allclose(
        rot @ np.swapaxes(rot, -1, -2), np.broadcast_to(np.eye(3), rot.shape), atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-12)
    np.testing.assert_allclose(rot[:, 0], np.broadcast_to(np.eye(3), (4, 3, 3)))  # the root
    from scipy.spatial.transform import Rotation

    for k in range(1, K):
        rest_bone = rest[k] - rest[parents[k]]
        bone = positions[:, k] - positions[:, parents[k]]
        turned = rot[:, k] @ rest_bone
        unit = bone / np.linalg.norm(bone, axis=-1, keepdims=True)
        np.testing.assert_allclose(turned / np.linalg.norm(rest_bone), unit, atol=1e-9)
        axis = Rotation.from_matrix(rot[:, k]).as_rotvec()  # no twist: the axis is normal
        np.testing.assert_allclose(axis @ rest_bone, 0.0, atol=1e-9)  # to the rest bone


def test_local_transforms_compose_back_to_the_world_transforms():
    rng = np.random.default_rng(2)
    from scipy.spatial.transform import Rotation

    rot = Rotation.random(3 * K, random_state=3).as_matrix().reshape(3, K, 3, 3)
    pos = rng.normal(size=(3, K, 3))
    local_rot, local_trans = rigmath.local_transforms(pos, rot, np.array(PARENTS))
    back_pos, back_rot = rigmath.compose(local_rot, local_trans, np.array(PARENTS))
    np.testing.assert_allclose(back_pos, pos, atol=1e-12)
    np.testing.assert_allclose(back_rot, rot, atol=1e-12)


def test_top_influences_keep_the_four_largest_renormalised():
    weights = np.array([[0.1, 0.3, 0.05, 0.25, 0.2, 0.1], [0.0, 0.0, 1.0, 0.0, 0.0, 0.0]])
    index, top = rigmath.top_influences(weights)
    assert index[0].tolist() == [1, 3, 4, 0]
    np.testing.assert_allclose(top[0], np.array([0.3, 0.25, 0.2, 0.1]) / 0.85, rtol=1e-6)
    assert top.dtype == np.float32 and np.all(top.sum(axis=1) == np.float32(1.0))
    assert index[1].tolist() == [2, 0, 0, 0] and top[1].tolist() == [1.0, 0.0, 0.0, 0.0]


@pytest.mark.parametrize("up_axis", [0, 1, 2])
def test_file_axes_put_the_data_up_axis_on_plus_y(up_axis):
    axes = rigmath.file_axes(up_axis)
    np.testing.assert_allclose(axes @ axes.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(axes) == pytest.approx(1.0)
    np.testing.assert_allclose(axes @ np.eye(3)[up_axis], [0.0, 1.0, 0.0])
    from nmjax.view import view_axes  # the side `nmjax view` shows becomes the front (+Z)

    up, towards, right = view_axes(up_axis)
    np.testing.assert_allclose(axes, np.stack([right, up, towards]))


# --- a retarget output: the skinned, animated character -----------------------------------------


def test_retarget_glb_joints_hierarchy_and_skinning_match_nmjax(retarget, tmp_path):
    out = tmp_path / "character.glb"
    assert export("--run", retarget, "--out", out) == 0
    doc, blob = load_gltf(out)
    with np.load(retarget / tasks.RETARGET_FILE) as z:
        joints, fps = z["joints"], float(z["frame_rate"])
    expected = in_file_axes(joints)  # (T, K, 3) nmjax's retargeted joints (Eqs. 24-25)
    names = [doc.nodes[n].name for n in doc.skins[0].joints]
    assert sorted(names) == sorted(f"joint_{k}" for k in range(K))
    assert node_parents(doc) == {f"joint_{k}": f"joint_{p}" for k, p in enumerate(PARENTS)}
    times, positions = joint_positions(doc, blob)
    np.testing.assert_allclose(times, np.arange(len(joints)) / fps, rtol=1e-6)
    size = size_of(expected)
    for k in range(K):
        np.testing.assert_allclose(
            positions[f"joint_{k}"], expected[:, k], atol=FK_TOLERANCE * size
        )
    # The mesh: glTF's skinning equation against nmjax's LBS of the target mesh (the frames).
    frames = in_file_axes(tasks.read_retarget(retarget)["vertices"])
    skinned, weights = skinned_vertices(doc, blob)
    np.testing.assert_allclose(weights.sum(axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(skinned, frames, atol=SKIN_TOLERANCE * size_of(frames))
    assert_no_validator_errors(out)


def test_gltf_json_holds_the_same_character(retarget, tmp_path):
    glb, gltf = tmp_path / "a.glb", tmp_path / "a.gltf"
    assert export("--run", retarget, "--out", glb) == 0
    assert export("--run", retarget, "--out", gltf, "--fps", "24") == 0
    (doc_b, blob_b), (doc_j, blob_j) = load_gltf(glb), load_gltf(gltf)
    assert node_parents(doc_j) == node_parents(doc_b)
    times, from_json = joint_positions(doc_j, blob_j)
    _, from_glb = joint_positions(doc_b, blob_b)
    np.testing.assert_allclose(times, np.arange(len(times)) / 24.0, rtol=1e-6)  # --fps
    for name, position in from_glb.items():
        np.testing.assert_array_equal(from_json[name], position)
    np.testing.assert_array_equal(
        skinned_vertices(doc_j, blob_j)[0], skinned_vertices(doc_b, blob_b)[0]
    )
    assert_no_validator_errors(gltf)


def test_bvh_read_by_bvhio_puts_every_joint_where_nmjax_does(retarget, tmp_path):
    import bvhio

    out = tmp_path / "character.bvh"
    assert export("--run", retarget, "--out", out) == 0
    text = out.read_text()
    assert "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation" in text
    with np.load(retarget / tasks.RETARGET_FILE) as z:
        expected, fps = in_file_axes(z["joints"]), float(z["frame_rate"])
    container = bvhio.readAsBvh(str(out))
    assert container.FrameCount == len(expected)
    assert container.FrameTime == pytest.approx(1.0 / fps)
    root = bvhio.readAsHierarchy(str(out))
    layout = root.layout()
    parent_of = {j.Name: (j.Parent.Name if j.Parent else j.Name) for j, _, _ in layout}
    assert parent_of == {f"joint_{k}": f"joint_{p}" for k, p in enumerate(PARENTS)}
    size = size_of(expected)
    for t in range(len(expected)):
        root.loadPose(t)
        for joint, _, _ in layout:
            k = int(joint.Name.split("_")[1])
            np.testing.assert_allclose(
                np.array(joint.PositionWorld), expected[t, k], atol=FK_TOLERANCE * size
            )


# --- runs with --seq, task outputs ----------------------------------------------------------------


def test_phase2_run_exports_its_reconstruction_of_a_sequence(runs, tmp_path):
    import jax
    import jax.numpy as jnp
    from flax import nnx

    from nmjax import run_folder
    from nmjax.train import trained as run_folders

    name = sorted(run_folder.load_trajectories(runs["skel"], "test"))[0]
    out = tmp_path / "recon.glb"
    assert export("--run", runs["nm"], "--seq", name, "--out", out) == 0
    model = run_folders.restore_dynamics(runs["nm"])
    x = run_folder.load_trajectories(runs["skel"], "test")[name][None]
    _, recon = tasks.infer_rotations_jit(*nnx.split(model), jnp.asarray(x), jax.random.key(0))
    expected = in_file_axes(np.asarray(recon[0, ..., :3]))  # the decoder's FK (Eq. 2)
    doc, blob = load_gltf(out)
    _, positions = joint_positions(doc, blob)
    size = size_of(expected)
    for k in range(K):
        np.testing.assert_allclose(
            positions[f"joint_{k}"], expected[:, k], atol=FK_TOLERANCE * size
        )
    assert_no_validator_errors(out)


def test_phase1_run_exports_keypoints_with_swing_rotations(runs, tmp_path):
    from nmjax import run_folder

    trajectories = run_folder.load_trajectories(runs["skel"], "test")
    name = sorted(trajectories)[0]
    out = tmp_path / "keypoints.glb"
    assert export("--run", runs["skel"], "--seq", name, "--out", out, "--up", "y") == 0
    keypoints = in_file_axes(trajectories[name][..., :3], up_axis=1)
    doc, blob = load_gltf(out)
    _, world = world_matrices(doc, blob)
    by_name = {doc.nodes[n].name: world[n] for n in doc.skins[0].joints}
    size = size_of(keypoints)
    for k, p in enumerate(PARENTS):
        np.testing.assert_allclose(
            by_name[f"joint_{k}"][:, :3, 3], keypoints[:, k], atol=FK_TOLERANCE * size
        )
        if k == p:
            continue
        # Swing only: the joint's rotation since frame 0 turns its first bone onto its bone.
        turn = by_name[f"joint_{k}"][:, :3, :3] @ by_name[f"joint_{k}"][0, :3, :3].T
        first, bone = keypoints[0, k] - keypoints[0, p], keypoints[:, k] - keypoints[:, p]
        turned = turn @ (first / np.linalg.norm(first))
        unit = bone / np.linalg.norm(bone, axis=-1, keepdims=True)
        np.testing.assert_allclose(turned, unit, atol=1e-5)
    assert_no_validator_errors(out)


def test_phase1_run_exports_the_refined_skeleton_of_a_refined_sequence(runs, tmp_path, capsys):
    import shutil

    from nmjax import run_folder
    from nmjax.export.refine import refine_run
    from nmjax.skeleton_refine import RefineSettings

    run = tmp_path / "skel"
    shutil.copytree(runs["skel"], run)
    settings = RefineSettings(iterations=2, surface_points=64, target_points=64)
    (done,) = refine_run(run, settings=settings, progress=False)
    refined = run_folder.read_refined(run, "test", done.name)
    out = tmp_path / "refined.glb"
    assert export("--run", run, "--seq", done.name, "--out", out, "--up", "y") == 0
    assert capsys.readouterr().out.strip().endswith("(the refined skeleton)")
    axes = rigmath.file_axes(1)
    positions = in_file_axes(refined["positions"], up_axis=1)
    doc, blob = load_gltf(out)
    assert doc.animations[0].name == f"{done.name}_refined"
    _, world = world_matrices(doc, blob)
    by_name = {doc.nodes[n].name: world[n] for n in doc.skins[0].joints}
    size = size_of(positions)
    for j, k in enumerate(refined["joints"]):
        # The refined joints and their full rotations (with twist), in the file's axes.
        np.testing.assert_allclose(
            by_name[f"joint_{k}"][:, :3, 3], positions[:, j], atol=FK_TOLERANCE * size
        )
        rotation = axes @ refined["rotations"][:, j] @ axes.T
        np.testing.assert_allclose(by_name[f"joint_{k}"][:, :3, :3], rotation, atol=1e-5)
    lengths = np.linalg.norm(positions - positions[:, refined["parents"]], axis=-1)
    assert np.max(lengths.std(axis=0)) < 1e-6
    assert_no_validator_errors(out)
    # --unrefined: the detector's keypoints again, whatever is stored.
    argv = ["--run", run, "--seq", done.name, "--out", tmp_path / "kp.glb", "--up", "y"]
    assert export(*argv, "--unrefined") == 0
    assert "refined" not in capsys.readouterr().out
    doc, blob = load_gltf(tmp_path / "kp.glb")
    _, joints = joint_positions(doc, blob)
    keypoints = run_folder.load_trajectories(run, "test")[done.name][..., :3]
    keypoints = in_file_axes(keypoints, up_axis=1)
    for k in range(K):
        np.testing.assert_allclose(joints[f"joint_{k}"], keypoints[:, k], atol=FK_TOLERANCE * size)
    assert export("--run", run, "--seq", done.name, "--out", tmp_path / "refined.bvh") == 0
    assert "(the refined skeleton)" in capsys.readouterr().out
    line = refused(
        capsys, tmp_path / "x.glb", "--run", runs["nm"], "--seq", done.name, "--unrefined"
    )
    assert "--unrefined" in line and "phase-1" in line


def write_generate_output(folder, keep):
    """A generate.npz as `nmjax generate` writes it (2 inputs, 3 samples, 5 frames)."""
    rng = np.random.default_rng(4)
    folder.mkdir()
    keypoints = rng.uniform(-0.8, 0.8, (2, 3, 5, K, 4)).astype(np.float32)
    np.savez(
        folder / "generate.npz",
        keypoints=keypoints,
        observed=keypoints[:, 0],
        observed_frames=np.array([5, 5], np.int32),
        names=np.array(["seq_a", "seq_b"]),
        parents=np.array(PARENTS),
        cond=np.int32(2),
        frame_rate=np.float64(12.5),
        up_axis=np.int64(2),
        keep=np.asarray(keep),
    )
    return keypoints


def test_generate_output_exports_one_sample_of_the_kept_nodes(tmp_path):
    keep = np.ones(K, bool)
    keep[2] = False  # joint 3 hangs off joint 1 once 2 is pruned
    keypoints = write_generate_output(tmp_path / "gen", keep)
    out = tmp_path / "sample.glb"
    assert export("--run", tmp_path / "gen", "--seq", "seq_b", "--sample", "2", "--out", out) == 0
    doc, blob = load_gltf(out)
    expected_parents = {0: 0, 1: 0, 3: 1, 4: 1, 5: 4}
    assert node_parents(doc) == {f"joint_{k}": f"joint_{p}" for k, p in expected_parents.items()}
    times, positions = joint_positions(doc, blob)
    np.testing.assert_allclose(times, np.arange(5) / 12.5, rtol=1e-6)
    expected = in_file_axes(keypoints[1, 2, ..., :3])
    for k in expected_parents:
        np.testing.assert_allclose(
            positions[f"joint_{k}"], expected[:, k], atol=FK_TOLERANCE * size_of(expected)
        )
    assert_no_validator_errors(out)


def test_interpolate_output_exports_the_chosen_method(tmp_path):
    rng = np.random.default_rng(5)
    folder = tmp_path / "interp"
    folder.mkdir()
    motions = {m: rng.uniform(-0.5, 0.5, (1, 4, K, 4)).astype(np.float32) for m in ("Ours", "Lerp")}
    np.savez(
        folder / "interpolate.npz",
        names=np.array(["s"]),
        parents=np.array(PARENTS),
        truth=motions["Ours"],
        **motions,
    )
    out = tmp_path / "lerp.bvh"
    assert export("--run", folder, "--method", "Lerp", "--out", out) == 0
    import bvhio

    root = bvhio.readAsHierarchy(str(out))
    expected = in_file_axes(motions["Lerp"][0, ..., :3])  # older files: z up, 30 fps
    assert bvhio.readAsBvh(str(out)).FrameTime == pytest.approx(1.0 / 30.0)
    for t in range(4):
        root.loadPose(t)
        for joint, _, _ in root.layout():
            k = int(joint.Name.split("_")[1])
            np.testing.assert_allclose(
                np.array(joint.PositionWorld), expected[t, k], atol=1e-5 * size_of(expected)
            )


# --- the viewer opens an exported file ------------------------------------------------------------


def test_view_opens_an_exported_glb_and_plays_its_frames(retarget, tmp_path):
    from nmjax import view

    out = tmp_path / "character.glb"
    assert export("--run", retarget, "--out", out) == 0
    doc, blob = load_gltf(out)
    _, positions = joint_positions(doc, blob)
    skinned, _ = skinned_vertices(doc, blob)
    viewer = view.open_view(out, port=0)
    try:
        assert viewer.kind == "glTF file" and viewer.num_frames == len(skinned)
        assert {"/gltf/mesh", "/gltf/keypoints", "/gltf/skeleton/bones"} <= set(viewer.nodes)
        viewer.frame.value = 2  # the slider redraws
        names = [doc.nodes[n].name for n in doc.skins[0].joints]
        shown = np.asarray(viewer.pose.keypoints.batched_positions)
        expected = np.stack([positions[name][2] for name in names])
        np.testing.assert_allclose(shown, expected, atol=1e-5)
        np.testing.assert_allclose(np.asarray(viewer.mesh.vertices), skinned[2], atol=1e-5)
    finally:
        viewer.stop()


# --- refused inputs: one line, exit status 2, nothing written ------------------------------------


def refused(capsys, out, *argv):
    """Runs `nmjax export ... --out out`, checks the refusal and returns its line."""
    before = out.read_bytes() if out.exists() else None
    assert export(*argv, "--out", out) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("nmjax export: ")
    assert (out.read_bytes() if out.exists() else None) == before
    assert not list(out.parent.glob(f".{out.name}.*"))  # no temporary file left
    return err


def test_bad_inputs_are_refused_in_one_line(runs, retarget, tmp_path, capsys):
    out = tmp_path / "out.glb"
    for run in (runs["nm"], runs["skel"]):  # a run holds many motions
        assert "--seq NAME" in refused(capsys, out, "--run", run)
    assert "'nope'" in refused(capsys, out, "--run", runs["skel"], "--seq", "nope")
    write_generate_output(tmp_path / "gen", np.ones(K, bool))
    line = refused(capsys, out, "--run", tmp_path / "gen", "--sample", "3")
    assert "--sample 3 is out of range" in line and "3 samples" in line
    assert "--sample" in refused(capsys, out, "--run", retarget, "--sample", "0")
    line = refused(capsys, tmp_path / "rig.fbx", "--run", retarget)
    assert "'.fbx'" in line and ".glb" in line and ".bvh" in line
    assert "does not exist" in refused(capsys, out, "--run", tmp_path / "missing")
    out.write_bytes(b"keep me")
    assert "--overwrite" in refused(capsys, out, "--run", retarget)
    assert export("--run", retarget, "--out", out, "--overwrite") == 0
    assert out.read_bytes()[:4] == b"glTF"
    # A retarget output of an older nmjax, without the rig: named, with the command that fixes it.
    old = tmp_path / "old"
    old.mkdir()
    with np.load(retarget / tasks.RETARGET_FILE) as z:
        np.savez(
            old / tasks.RETARGET_FILE,
            **{k: z[k] for k in ("joints", "parents", "skin_weights", "source")},
        )
    assert "nmjax retarget" in refused(capsys, tmp_path / "old.glb", "--run", old)
