"""nmjax.data.body_models: the restricted model-file reader and the SMPL / MANO forward pass,
checked on tiny models whose results can be worked out by hand."""

from __future__ import annotations

import os
import pickle

import numpy as np
import pytest
import scipy.sparse
from body_model_files import (
    MANO_PARENTS,
    SMPL_PARENTS,
    box_model,
    chain_model,
    kintree,
    tree_joints,
    write_npz,
    write_official_pkl,
)

from nmjax import geometry
from nmjax.data import body_models

QUARTER = np.pi / 2


def chain_files(tmp_path, posedirs_scale=0.0, protocol=2):
    arrays = chain_model(posedirs_scale)
    return (
        arrays,
        write_npz(tmp_path / "chain.npz", arrays),
        write_official_pkl(tmp_path / "chain.pkl", arrays, protocol),
    )


@pytest.mark.parametrize("protocol", [0, 2])
def test_pkl_and_npz_read_as_the_same_model(tmp_path, protocol):
    arrays, npz, pkl = chain_files(tmp_path, posedirs_scale=0.1, protocol=protocol)
    for path in (npz, pkl):
        model = body_models.load_model(path)
        np.testing.assert_array_equal(model.v_template, arrays["v_template"])
        np.testing.assert_array_equal(model.shapedirs, arrays["shapedirs"])
        np.testing.assert_array_equal(model.posedirs, arrays["posedirs"])
        np.testing.assert_array_equal(model.j_regressor, arrays["J_regressor"])
        np.testing.assert_array_equal(model.weights, arrays["weights"])
        np.testing.assert_array_equal(model.faces, arrays["f"])
        np.testing.assert_array_equal(model.parents, [0, 0, 1])  # the root its own parent
        assert model.hands_mean is None and model.kind == "a 3-joint model"


def test_rotating_the_child_joint_moves_only_its_vertices(tmp_path):
    _, npz, _ = chain_files(tmp_path)
    model = body_models.load_model(npz)
    pose = np.zeros(9)
    pose[3:6] = [0.0, 0.0, QUARTER]  # joint 1 (at x = 1) turns 90 degrees about z
    vertices, joints = body_models.pose_model(model, pose)
    expected = [
        [0.0, 0.0, 0.0],  # marker of the root: unmoved
        [1.0, 0.0, 0.0],  # the rotating joint itself
        [1.0, 1.0, 0.0],  # joint 2, one unit along the turned bone
        [0.5, 0.1, 0.0],  # weighted to joint 0: unmoved
        [0.9, 0.5, 0.0],  # (1.5, 0.1): (0.5, 0.1) from joint 1 turns to (-0.1, 0.5)
        [1.3, 0.2, 0.0],  # half of (1.5, -0.1) and half of its turned place (1.1, 0.5)
        [1.0, 1.5, 0.0],  # (2.5, 0): follows joint 2, 1.5 from joint 1 along the turned bone
    ]
    np.testing.assert_allclose(vertices, expected, atol=1e-12)
    np.testing.assert_allclose(joints, [[0, 0, 0], [1, 0, 0], [1, 1, 0]], atol=1e-12)


def test_root_rotation_and_translation(tmp_path):
    _, npz, _ = chain_files(tmp_path)
    model = body_models.load_model(npz)
    pose = np.zeros((2, 9))
    pose[1, :3] = [0.0, 0.0, np.pi]  # frame 1: the whole body half a turn about z through joint 0
    trans = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]])
    vertices, joints = body_models.pose_model(model, pose, trans=trans)
    np.testing.assert_allclose(vertices[0], model.v_template, atol=1e-12)
    turned = model.v_template * [-1.0, -1.0, 1.0] + [1.0, 2.0, 3.0]
    np.testing.assert_allclose(vertices[1], turned, atol=1e-12)
    np.testing.assert_allclose(joints[1], [[1, 2, 3], [0, 2, 3], [-1, 2, 3]], atol=1e-12)


def test_pose_blend_is_zero_at_rest_and_added_before_skinning(tmp_path):
    arrays, npz, _ = chain_files(tmp_path, posedirs_scale=0.1)
    model = body_models.load_model(npz)
    rest, _ = body_models.pose_model(model, np.zeros(9))
    np.testing.assert_allclose(rest, arrays["v_template"], atol=1e-15)
    pose = np.zeros(9)
    pose[3:6] = [0.0, 0.0, QUARTER]
    posed, _ = body_models.pose_model(model, pose)
    # R - I of the quarter turn about z, row by row; joint 2 is at rest (zeros).
    feature = np.array([-1, -1, 0, 1, -1, 0, 0, 0, 0] + [0] * 9, dtype=np.float64)
    # Vertex 3 follows the unmoved root: only its blend-shape offset moves it.
    np.testing.assert_allclose(posed[3], arrays["v_template"][3] + arrays["posedirs"][3] @ feature)
    rotations = geometry.axis_angle_to_matrix_np(pose.reshape(3, 3))
    np.testing.assert_allclose(
        body_models.pose_blend(arrays["posedirs"], rotations), arrays["posedirs"] @ feature
    )


def test_betas_shift_the_template_linearly(tmp_path):
    arrays, _, pkl = chain_files(tmp_path)
    model = body_models.load_model(pkl)
    betas = np.array([0.3, -0.7])
    zero = np.zeros(9)
    shaped, joints = body_models.pose_model(model, zero, betas=betas)
    expected = arrays["v_template"] + 0.3 * arrays["shapedirs"][..., 0]
    expected -= 0.7 * arrays["shapedirs"][..., 1]
    np.testing.assert_allclose(shaped, expected, atol=1e-12)
    np.testing.assert_allclose(joints, expected[:3], atol=1e-12)  # the markers are the joints
    double, _ = body_models.pose_model(model, zero, betas=2 * betas)
    np.testing.assert_allclose(double - arrays["v_template"], 2 * (shaped - arrays["v_template"]))
    # Fewer betas than the model has: the rest are zero.
    first, _ = body_models.pose_model(model, zero, betas=betas[:1])
    np.testing.assert_allclose(first, arrays["v_template"] + 0.3 * arrays["shapedirs"][..., 0])


def test_regressed_joints_of_a_posed_smpl_tree_are_its_chain_joints(tmp_path):
    rest = tree_joints(SMPL_PARENTS, bone=0.2)
    path = write_official_pkl(tmp_path / "smpl.pkl", box_model(SMPL_PARENTS, rest, half=0.02))
    model = body_models.load_model(path)
    assert model.kind == "SMPL" and model.parents.tolist() == [0, *SMPL_PARENTS[1:]]
    pose = np.random.default_rng(1).normal(scale=0.5, size=(4, 72))
    vertices, joints = body_models.pose_model(model, pose, betas=np.ones(3), trans=np.ones(3))
    regressed = body_models.regress_joints(model.j_regressor, vertices)
    np.testing.assert_allclose(regressed, joints, atol=1e-12)
    # Bones keep their length under any pose.
    bones = np.linalg.norm(joints[:, 1:] - joints[:, model.parents[1:]], axis=-1)
    np.testing.assert_allclose(bones, np.broadcast_to(bones[:1], bones.shape), atol=1e-12)


def test_mano_pose_adds_the_mean_hand(tmp_path):
    arrays = box_model(MANO_PARENTS, tree_joints(MANO_PARENTS, bone=0.03), half=0.004)
    arrays["hands_mean"] = np.linspace(-0.2, 0.2, 45)
    model = body_models.load_model(write_npz(tmp_path / "mano.npz", arrays))
    assert model.kind == "MANO"
    stored = np.zeros((2, 48))
    stored[:, :3] = [0.1, 0.2, 0.3]
    full = body_models.mano_pose(model, stored)
    np.testing.assert_array_equal(full[:, :3], stored[:, :3])
    np.testing.assert_allclose(full[:, 3:], np.broadcast_to(arrays["hands_mean"], (2, 45)))
    without = dict(arrays)
    del without["hands_mean"]
    plain = body_models.load_model(write_npz(tmp_path / "plain.npz", without))
    with pytest.raises(ValueError, match="no 'hands_mean'"):
        body_models.mano_pose(plain, stored)


def test_kintree_table_order_and_errors():
    table = kintree([-1, 0, 1, 1])[:, [2, 0, 3, 1]]  # columns in any order
    np.testing.assert_array_equal(body_models.parents_from_kintree(table), [0, 0, 1, 1])
    for root in (-1, 0, 2**32 - 1):  # signed, own id, unsigned 32-bit
        table = np.array([[root, 0, 1], [0, 1, 2]], dtype=np.int64)
        np.testing.assert_array_equal(body_models.parents_from_kintree(table), [0, 0, 1])
    with pytest.raises(ValueError, match=r"2 roots \(entries \[0, 1\]\)"):
        body_models.parents_from_kintree(kintree([-1, -1, 0]))
    with pytest.raises(ValueError, match=r"entries \[1, 2\] never reach the root"):
        body_models.parents_from_kintree(np.array([[2**32 - 1, 2, 1], [0, 1, 2]]))
    with pytest.raises(ValueError, match="ids 0..K-1"):
        body_models.parents_from_kintree(np.array([[2**32 - 1, 0], [0, 5]]))


class RunsCode:
    """Unpickling this would run a shell command; the reader must refuse before calling it."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_pickles_holding_other_classes_are_refused(tmp_path):
    marker = tmp_path / "ran"
    arrays = chain_model()
    arrays["extra"] = RunsCode(marker)
    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps(arrays, protocol=2))
    with pytest.raises(ValueError, match=r"evil.pkl: holds a pickled posix\.system; refused"):
        body_models.load_model(path)
    assert not marker.exists()
    # An array subclass is another class too.
    records = np.rec.array([(1.0, 2.0)], dtype=[("a", float), ("b", float)])
    path.write_bytes(pickle.dumps({"v_template": records}))
    with pytest.raises(ValueError, match=r"holds a pickled numpy\S*\.recarray; refused"):
        body_models.load_model(path)


def test_restricted_load_reads_arrays_in_every_protocol():
    content = {
        "a": np.arange(6, dtype=np.float32).reshape(2, 3),
        "f": np.asfortranarray(np.arange(6.0).reshape(2, 3)),
        "s": np.float64(1.5),
        "csr": scipy.sparse.csr_matrix(np.eye(3)),
        "nested": [np.int32(3), ("text", {1, 2})],
    }
    for protocol in range(2, pickle.HIGHEST_PROTOCOL + 1):
        loaded = body_models.restricted_load(pickle.dumps(content, protocol=protocol), "mem")
        np.testing.assert_array_equal(loaded["a"], content["a"])
        assert loaded["a"].dtype == np.float32
        np.testing.assert_array_equal(loaded["f"], content["f"])
        assert loaded["s"] == 1.5 and loaded["nested"] == [3, ("text", {1, 2})]
        np.testing.assert_array_equal(loaded["csr"], np.eye(3))


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda a: a.pop("weights"), "no 'weights' array"),
        (lambda a: a.update(posedirs=a["posedirs"][..., :9]), r"'posedirs' has shape \(7, 3, 9\)"),
        (lambda a: a.update(f=a["f"] + 5), "'f' indexes vertices outside"),
        (lambda a: a.update(v_template=a["v_template"] * np.nan), "'v_template' contains NaN"),
        (lambda a: a.update(kintree_table=kintree([-1, -1, 0])), "exactly one root"),
    ],
)
def test_bad_model_files(tmp_path, change, match):
    arrays = chain_model()
    change(arrays)
    path = write_npz(tmp_path / "model.npz", arrays)
    with pytest.raises(ValueError, match=match):
        body_models.load_model(path)


def test_unreadable_model_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such file"):
        body_models.load_model(tmp_path / "missing.pkl")
    (tmp_path / "model.txt").write_text("x")
    with pytest.raises(ValueError, match=r"a \.pkl \(as downloaded\) or \.npz"):
        body_models.load_model(tmp_path / "model.txt")
    (tmp_path / "cut.pkl").write_bytes(pickle.dumps(chain_model(), protocol=2)[:200])
    with pytest.raises(ValueError, match="not a readable pickle"):
        body_models.load_model(tmp_path / "cut.pkl")
