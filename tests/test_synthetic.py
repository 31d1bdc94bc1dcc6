"""nmjax.data.synthetic and .bodies: bodies, kinematics, surface sampling, the written sets (C4)."""

from __future__ import annotations

import dataclasses
import fnmatch
import hashlib
import json
import tomllib
from pathlib import Path

import numpy as np
import pytest
import trimesh

from nmjax import atomic
from nmjax.data import bodies, layout, synthetic
from nmjax.data.datasets import load_sequences

NAMES = ("synth-hand", "synth-arm", "synth-human", "synth-quadruped")
TINY = {"num_sequences": 2, "frames": 5, "points": 2000, "progress": False}


def files_of(root):
    return {p.relative_to(root): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def reaches_root(parents: list[int], node: int) -> bool:
    for _ in range(len(parents)):
        if parents[node] == node:
            return True
        node = parents[node]
    return False


@pytest.mark.parametrize("name", NAMES)
def test_parents_form_a_tree(name):
    body = bodies.get_body(name)
    parents = body.parents
    assert len(parents) == len(body.joint_names) == len(set(body.joint_names))
    assert [i for i, p in enumerate(parents) if p == i] == [0]  # one root, its own parent
    assert all(0 <= p < len(parents) for p in parents)
    assert all(reaches_root(parents, j) for j in range(len(parents)))  # no cycles


def test_bodies_have_the_required_structure():
    assert set(bodies.BODIES) == set(NAMES)
    hand = bodies.get_body("synth-hand")
    assert len(hand.joints) >= 16
    for finger in ("thumb", "index", "middle", "ring", "pinky"):
        chain = [f"{finger}1", f"{finger}2", f"{finger}3", f"{finger}_tip"]
        index = [hand.joint_names.index(n) for n in chain]
        assert [hand.parents[i] for i in index[1:]] == index[:-1]  # three segments in a row
    arm = bodies.get_body("synth-arm")
    revolute = [arm.joints[j].name for j, d in arm.dofs if d.kind == "rotate"]
    assert revolute == [f"joint{i}" for i in range(1, 8)]
    assert {arm.joints[j].name for j, d in arm.dofs if d.kind == "slide"} == {
        "finger_left",
        "finger_right",
    }
    assert len(bodies.get_body("synth-human").joints) >= 15
    assert bodies.get_body("synth-human").speed > 0


@pytest.mark.parametrize("name", NAMES)
def test_bodies_are_about_unit_size(name):
    extent = np.ptp(synthetic.rest_mesh(bodies.get_body(name)).vertices, axis=0).max()
    assert 0.5 < extent < 1.6


def test_pose_bends_a_finger_like_a_planar_chain():
    hand = bodies.get_body("synth-hand")
    columns = [(hand.joints[j].name, d) for j, d in hand.dofs]
    angles = np.zeros((1, len(columns)))
    theta = 0.7
    # Flexion of the index knuckle (about its y axis) with every other angle zero.
    flex = next(i for i, (n, d) in enumerate(columns) if n == "index1" and d.axis[1] == 1.0)
    angles[0, flex] = theta
    positions, rotations = synthetic.pose(hand, angles, np.zeros((1, 3)))
    length = 0.19 + 0.12 + 0.09
    tip = positions[0, hand.joint_names.index("index_tip")]
    np.testing.assert_allclose(tip, [0.35 + length * np.cos(theta), 0.12, -length * np.sin(theta)])
    np.testing.assert_allclose(rotations[0, 0], np.eye(3), atol=1e-12)
    # Every frame is a rotation matrix.
    np.testing.assert_allclose(
        np.einsum("tjki,tjkl->tjil", rotations, rotations),
        np.broadcast_to(np.eye(3), rotations.shape),
        atol=1e-12,
    )


def test_pose_slides_the_gripper_fingers_and_follows_the_root():
    arm = bodies.get_body("synth-arm")
    angles = np.zeros((2, len(arm.dofs)))
    for column, (_, dof) in enumerate(arm.dofs):
        if dof.kind == "slide":
            angles[1, column] = 0.03
    shift = np.array([[0.0, 0.0, 0.0], [0.2, -0.1, 0.05]])
    positions, _ = synthetic.pose(arm, angles, shift)
    hand = positions[:, arm.joint_names.index("hand")]
    left = positions[:, arm.joint_names.index("finger_left")]
    right = positions[:, arm.joint_names.index("finger_right")]
    np.testing.assert_allclose(left - hand, [[0, 0.025, -0.06], [0, 0.055, -0.06]], atol=1e-12)
    np.testing.assert_allclose(right - hand, [[0, -0.025, -0.06], [0, -0.055, -0.06]], atol=1e-12)
    np.testing.assert_allclose(positions[:, 0], shift, atol=1e-12)


@pytest.mark.parametrize("name", NAMES)
def test_motion_respects_limits_and_is_visible(name):
    body = bodies.get_body(name)
    angles, root = synthetic.sample_motion(body, 60, np.random.default_rng(3))
    assert angles.shape == (60, len(body.dofs)) and root.shape == (60, 3)
    limits = body.limits
    assert np.all(angles >= limits[:, 0]) and np.all(angles <= limits[:, 1])
    rotate = np.array([d.kind == "rotate" for _, d in body.dofs])
    span = np.ptp(angles[:, rotate], axis=0)
    assert np.median(span) > np.radians(15)  # several tens of degrees for a typical joint
    # Smooth: accelerations are small next to velocities (white noise would give a ratio near
    # 2), and no joint jumps by more than a small part of the (unit-sized) body per frame.
    velocity, acceleration = np.diff(angles, axis=0), np.diff(angles, 2, axis=0)
    assert np.abs(acceleration).max() < 0.35 * np.abs(velocity).max()
    positions, _ = synthetic.pose(body, angles, root)
    assert np.abs(np.diff(positions, axis=0)).max() < 0.15


def test_human_root_translates():
    body = bodies.get_body("synth-human")
    moved = [
        np.linalg.norm(
            np.ptp(synthetic.sample_motion(body, 60, np.random.default_rng(s))[1], axis=0)
        )
        for s in range(4)
    ]
    assert max(moved) > 0.1


@pytest.mark.parametrize("name", NAMES)
def test_every_joint_lies_within_the_sampled_body(name):
    body = bodies.get_body(name)
    sequence = synthetic.simulate(name, 5, points=2000, rng=11)
    radius = np.array([j.radius for j in body.joints])
    # (T, J, N) distances from every joint to every sampled point of its frame.
    distance = np.linalg.norm(sequence.joints[:, :, None] - sequence.vertices[:, None], axis=-1)
    ratio = distance.min(-1) / radius
    assert ratio.max() < 1.5, body.joint_names[int(np.argmax(ratio.max(0)))]


@pytest.mark.parametrize("name", ["synth-hand", "synth-quadruped"])
def test_samples_lie_on_the_surface_area_uniformly(name):
    body = bodies.get_body(name)
    positions, rotations = synthetic.pose(body, np.zeros((1, len(body.dofs))), np.zeros((1, 3)))
    rng = np.random.default_rng(0)
    points = synthetic.sample_body_surface(body, positions, rotations, 20000, rng)[0]
    mesh = synthetic.rest_mesh(body)
    _, distance, _ = trimesh.proximity.closest_point(mesh, points[:2000])
    assert distance.max() < 1e-5
    # Same distribution as trimesh's own area-weighted sampler: compare slab histograms.
    reference = trimesh.sample.sample_surface(mesh, 20000, seed=1)[0]
    for axis in range(3):
        edges = np.linspace(mesh.bounds[0, axis] - 1e-4, mesh.bounds[1, axis] + 1e-4, 9)
        ours = np.histogram(points[:, axis], edges)[0] / len(points)
        theirs = np.histogram(reference[:, axis], edges)[0] / len(reference)
        np.testing.assert_allclose(ours, theirs, atol=0.012)


def test_generate_writes_the_layout(tmp_path):
    root = synthetic.generate(
        "synth-arm", tmp_path / "arm", num_sequences=3, frames=6, points=500, seed=5, progress=False
    )
    split = json.loads((root / "split.json").read_text())
    assert split == {"train": ["seq_000", "seq_001"], "test": ["seq_002"]}
    body = bodies.get_body("synth-arm")
    meta = json.loads((root / "meta.json").read_text())
    assert meta["name"] == "synth-arm" and meta["complete"] is True
    assert meta["joint_names"] == body.joint_names and meta["parents"] == body.parents
    assert meta["sample_rate"] == 1 and meta["seed"] == 5 and meta["points"] == 500
    assert len(meta["dofs"]) == len(body.dofs)
    for name, seq in [("train", s) for s in split["train"]] + [("test", s) for s in split["test"]]:
        vertices = np.load(root / name / "vertices" / f"{seq}.npy")
        joints = np.load(root / name / "joints" / f"{seq}.npy")
        angles = np.load(root / name / "angles" / f"{seq}.npy")
        assert vertices.shape == (6, 500, 3) and vertices.dtype == np.float32
        assert joints.shape == (6, len(body.joints), 3) and joints.dtype == np.float32
        assert angles.shape == (6, len(body.dofs)) and angles.dtype == np.float32
        limits = np.array([d["limits"] for d in meta["dofs"]], dtype=np.float32)
        assert np.all(angles >= limits[:, 0]) and np.all(angles <= limits[:, 1])
        assert np.isfinite(vertices).all()
    assert layout.is_complete(root)
    assert not list(root.rglob("*.tmp"))


def test_split_is_nine_to_one_with_at_least_one_test_sequence():
    assert [len(v) for v in layout.split_names(2).values()] == [1, 1]
    assert [len(v) for v in layout.split_names(30).values()] == [27, 3]
    assert [len(v) for v in layout.split_names(40).values()] == [36, 4]


def test_generate_is_deterministic(tmp_path):
    a = synthetic.generate("synth-hand", tmp_path / "a", seed=7, **TINY)
    b = synthetic.generate("synth-hand", tmp_path / "b", seed=7, **TINY)
    c = synthetic.generate("synth-hand", tmp_path / "c", seed=8, **TINY)
    files_a = files_of(a)
    assert files_a == files_of(b)
    vertices = Path("train/vertices/seq_000.npy")
    assert files_a[vertices] != files_of(c)[vertices]


def test_regeneration_removes_stale_sequences(tmp_path):
    root = synthetic.generate(
        "synth-human", tmp_path / "h", num_sequences=4, frames=3, points=200, progress=False
    )
    assert (root / "train/vertices/seq_002.npy").exists()
    synthetic.generate("synth-human", root, num_sequences=2, frames=3, points=200, progress=False)
    assert sorted(p.name for p in (root / "train/vertices").iterdir()) == ["seq_000.npy"]
    assert sorted(p.name for p in (root / "test/joints").iterdir()) == ["seq_001.npy"]


def test_interrupted_generation_is_not_complete(tmp_path, monkeypatch):
    root = synthetic.generate("synth-quadruped", tmp_path / "q", seed=1, **TINY)
    assert layout.is_complete(root)
    calls = []
    real_save = atomic.save_npy

    def save_then_interrupt(path, array):
        calls.append(path)
        if len(calls) == 4:
            raise KeyboardInterrupt
        real_save(path, array)

    monkeypatch.setattr(atomic, "save_npy", save_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        synthetic.generate("synth-quadruped", root, seed=2, **TINY)
    assert not layout.is_complete(root)
    assert not (root / "meta.json").exists()
    monkeypatch.setattr(atomic, "save_npy", real_save)
    synthetic.generate("synth-quadruped", root, seed=2, **TINY)
    assert layout.is_complete(root)
    assert files_of(root) == files_of(
        synthetic.generate("synth-quadruped", tmp_path / "fresh", seed=2, **TINY)
    )


def test_is_complete_rejects_missing_or_unfinished_meta(tmp_path):
    assert not layout.is_complete(tmp_path)
    (tmp_path / "meta.json").write_text('{"name": "synth-hand", "complete": false}')
    assert not layout.is_complete(tmp_path)
    (tmp_path / "meta.json").write_text('{"name": "synth-ha')
    assert not layout.is_complete(tmp_path)


def test_bad_arguments_name_the_problem(tmp_path):
    with pytest.raises(ValueError, match="synth-hand"):
        synthetic.generate("synth-snake", tmp_path)
    with pytest.raises(ValueError, match="num_sequences"):
        synthetic.generate("synth-hand", tmp_path, num_sequences=1)
    with pytest.raises(ValueError, match="frames"):
        synthetic.generate("synth-hand", tmp_path, frames=1)
    with pytest.raises(ValueError, match=r"\(T, 23\)"):
        synthetic.pose(bodies.get_body("synth-hand"), np.zeros((2, 3)), np.zeros((2, 3)))


def test_ensure_dataset_generates_only_a_set_that_is_missing_or_unfinished(tmp_path):
    root = tmp_path / "arm"
    with pytest.raises(
        FileNotFoundError, match=f"nmjax prepare-data --data synth-arm --root {root}"
    ):
        load_sequences("synth-arm", "train", root)
    assert not root.exists()  # loading never writes
    assert synthetic.ensure_dataset("synth-arm", root, seed=3, **TINY) == root
    assert layout.is_complete(root)
    assert [s.name for s in load_sequences("synth-arm", "train", root)] == ["seq_000"]
    finished = files_of(root)
    synthetic.ensure_dataset("synth-arm", root, seed=4, **TINY)  # finished: left as it is
    assert files_of(root) == finished

    (root / "meta.json").unlink()  # as an interrupted generation leaves it
    with pytest.raises(FileNotFoundError, match="--overwrite") as err:
        load_sequences("synth-arm", "test", root)
    assert "complete" in str(err.value)
    synthetic.ensure_dataset("synth-arm", root, seed=3, **TINY)
    assert files_of(root) == finished


def test_ensure_dataset_resolves_the_default_root_and_leaves_real_sets_alone(tmp_path, monkeypatch):
    monkeypatch.setenv("NMJAX_DATA", str(tmp_path))
    assert synthetic.ensure_dataset("synth-hand", **TINY) == tmp_path / "synth-hand"
    assert layout.is_complete(tmp_path / "synth-hand")
    assert synthetic.ensure_dataset("dfaust") == tmp_path / "dfaust"
    assert not (tmp_path / "dfaust").exists()  # real sets come from `nmjax prepare-data --from`
    with pytest.raises(ValueError, match="valid names"):
        synthetic.ensure_dataset("synth-snake")


# Computed from the bodies when their tables were Python code (before bodies.json): a digest of
# every value of the four bodies, and the sums of a generated sequence of each.
TABLES_SHA256 = "fad8cf67940394573b4a431cdfd35bb10114fcf2fadb3e9afa83ce39173a26cb"
GENERATED_SUMS = {  # simulate(name, 7, points=300, rng=5): vertices, joints, angles
    "synth-hand": (580.7990321738671, 44.79214786470402, 76.99095349456184),
    "synth-arm": (1014.2072831490186, 61.05870482089813, 6.1869245887501165),
    "synth-human": (1279.3248998016752, 74.85726693442848, 46.281036577755),
    "synth-quadruped": (1104.5729627907067, 66.75805660162587, 19.877130744498572),
}


def test_the_shipped_tables_are_the_bodies_the_code_held():
    values = repr([dataclasses.astuple(body) for body in bodies.BODIES.values()])
    assert hashlib.sha256(values.encode()).hexdigest() == TABLES_SHA256
    assert list(bodies.BODIES) == list(GENERATED_SUMS)
    for name, sums in GENERATED_SUMS.items():
        seq = synthetic.simulate(name, 7, points=300, rng=5)
        got = [np.asarray(a, np.float64).sum() for a in (seq.vertices, seq.joints, seq.angles)]
        np.testing.assert_allclose(got, sums, rtol=1e-6, err_msg=name)


def test_the_tables_ship_with_the_package():
    pyproject = Path(__file__).parents[1] / "pyproject.toml"
    globs = tomllib.loads(pyproject.read_text())["tool"]["setuptools"]["package-data"]
    assert any(fnmatch.fnmatch(bodies.BODIES_FILE, g) for g in globs["nmjax.data"])


def test_a_malformed_table_is_named():
    text = (Path(bodies.__file__).parent / bodies.BODIES_FILE).read_text()
    tables = json.loads(text)
    assert bodies.read_bodies(text) == bodies.BODIES
    del tables["bodies"]["synth-arm"]["joints"][1]["offset"]
    with pytest.raises(ValueError, match="bodies.json: body 'synth-arm' has a malformed entry"):
        bodies.read_bodies(json.dumps(tables))
    tables = json.loads(text)
    tables["bodies"]["synth-hand"]["joints"][2]["parent"] = "nowhere"
    with pytest.raises(ValueError, match="synth-hand: parent 'nowhere'"):
        bodies.read_bodies(json.dumps(tables))
