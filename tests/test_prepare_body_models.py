"""`nmjax prepare-data --data aist / hanco --body-model FILE` on tiny downloads and tiny models.

The models are `body_model_files.box_model`s: one box per joint, skinned rigidly to it, so every
sampled point lies on the surface of a box around a posed joint, and J_regressor gives the posed
chain joints exactly. The AIST++ folder holds a train and a test sequence of the published split
and a third, damaged, one named in ignore_list.txt; the HanCo folder two sequences with a frame
without a fit, and a third with a single fit.
"""

from __future__ import annotations

import json
import pickle
import re

import numpy as np
import pytest
from body_model_files import (
    MANO_PARENTS,
    SMPL_PARENTS,
    box_model,
    tree_joints,
    write_npz,
    write_official_pkl,
)

from nmjax.cli import main as nmjax_main
from nmjax.data import body_models, hanco
from nmjax.data.datasets import load_sequences
from nmjax.data.layout import split_by_frames

POINTS = 64
SMPL_HALF, MANO_HALF = 0.03, 0.005  # half-size of each joint's box
TRAIN, TEST = "gKR_sBM_cAll_d29_mKR4_ch02", "gMH_sFM_cAll_d24_mMH2_ch21"  # published aist lists
IGNORED = "gHO_sBM_cAll_d21_mHO3_ch09"  # in the published train list too
AIST_FRAMES = {TRAIN: 5, TEST: 4}
SCALING = 93.0
# MANO's joints in HanCo's keypoint order (wrist, then thumb, index, middle, ring, pinky from the
# palm out); each fingertip keypoint sits at its finger's last joint.
MANO_TO_KEYPOINTS = [0, 13, 14, 15, 15, 1, 2, 3, 3, 4, 5, 6, 6, 10, 11, 12, 12, 7, 8, 9, 9]
HAS_FIT = [[True, True, False, True], [True, True, True], [False, True]]


def prepare(argv):
    return nmjax_main(["prepare-data", "--points", str(POINTS), *argv])


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    folder = tmp_path_factory.mktemp("models")
    smpl = box_model(SMPL_PARENTS, tree_joints(SMPL_PARENTS, bone=0.2), half=SMPL_HALF)
    mano = box_model(MANO_PARENTS, tree_joints(MANO_PARENTS, 0.03), half=MANO_HALF, betas=10)
    mano["hands_mean"] = np.random.default_rng(2).normal(scale=0.2, size=45)
    return {
        "smpl": write_official_pkl(folder / "SMPL_MALE.pkl", smpl),
        "smpl_npz": write_npz(folder / "smpl.npz", smpl),
        "mano": write_official_pkl(folder / "MANO_RIGHT.pkl", mano),
    }


def motion(frames, seed):
    rng = np.random.default_rng(seed)
    return {
        "smpl_poses": rng.normal(scale=0.3, size=(frames, 72)).astype(np.float32),
        "smpl_trans": (SCALING * rng.normal(size=(frames, 3))).astype(np.float32),
        "smpl_scaling": np.array([SCALING]),
        "smpl_loss": 0.5,
    }


def write_aist(root, motions):
    (root / "motions").mkdir(parents=True)
    for name, content in motions.items():
        with open(root / "motions" / f"{name}.pkl", "wb") as f:
            pickle.dump(content, f)
    (root / "ignore_list.txt").write_text(f"{IGNORED}\n")


def aist_download(root):
    motions = {name: motion(count, seed) for seed, (name, count) in enumerate(AIST_FRAMES.items())}
    damaged = motion(3, 9)
    damaged["smpl_poses"] = damaged["smpl_poses"][:, :69]  # would be refused if it were read
    write_aist(root, {**motions, IGNORED: damaged})
    return motions


def check_on_boxes(points, centres, half):
    """Every point (T, N, 3) can be on the surface of a box of half-size `half` around one of the
    `centres` (T, J, 3) of its frame: between half and half * sqrt(3) away from it."""
    distance = np.linalg.norm(points[:, :, None] - centres[:, None], axis=-1)
    on_a_box = (distance >= half - 1e-5) & (distance <= half * np.sqrt(3) + 1e-5)
    assert on_a_box.any(axis=-1).all()


def test_aist_download(tmp_path, models, capsys):
    source, root = tmp_path / "aist", tmp_path / "out"
    motions = aist_download(source)
    argv = ["--data", "aist", "--from", str(source), "--root", str(root)]
    assert prepare([*argv, "--body-model", str(models["smpl"])]) == 0
    out = capsys.readouterr().out
    assert "2 sequences" in out and f"1 in ignore_list.txt, left out: {IGNORED}" in out
    assert json.loads((root / "split.json").read_text()) == {"train": [TRAIN], "test": [TEST]}
    meta = json.loads((root / "meta.json").read_text())
    assert meta["frames"] == AIST_FRAMES and meta["ignored"] == [IGNORED]
    # The prepared tree in nmjax's convention: the root (-1 in SMPL's table) its own parent.
    assert meta["parents"] == [0, *SMPL_PARENTS[1:]] and len(meta["joint_names"]) == 24
    model = body_models.load_model(models["smpl"])
    for split, name in (("train", TRAIN), ("test", TEST)):
        (seq,) = load_sequences("aist", split, root)
        frames, content = AIST_FRAMES[name], motions[name]
        assert seq.name == name and seq.vertices.shape == (frames, POINTS, 3)
        assert seq.joints.shape == (frames, 24, 3)
        # The root joint turns about itself: it sits at its rest place plus trans / scaling.
        trans = content["smpl_trans"].astype(np.float64) / SCALING
        rest = body_models.regress_joints(model.j_regressor, model.v_template)
        np.testing.assert_allclose(seq.joints[:, 0], rest[0] + trans, atol=1e-5)
        # Zero betas and rigid boxes: every bone keeps its rest length.
        bones = np.linalg.norm(seq.joints[:, 1:] - seq.joints[:, model.parents[1:]], axis=-1)
        rest_bones = np.linalg.norm(rest[1:] - rest[model.parents[1:]], axis=-1)
        np.testing.assert_allclose(bones, np.broadcast_to(rest_bones, bones.shape), atol=1e-5)
        _, chain = body_models.pose_model(model, content["smpl_poses"], trans=trans)
        np.testing.assert_allclose(seq.joints, chain, atol=1e-5)
        check_on_boxes(np.asarray(seq.vertices), np.asarray(seq.joints), SMPL_HALF)
    # The .npz conversion of the model gives the same bytes.
    again = tmp_path / "again"
    npz_argv = [*argv[:-1], str(again), "--body-model", str(models["smpl_npz"])]
    assert prepare(npz_argv) == 0
    for part in ("train/vertices", "train/joints", "test/vertices"):
        first = (root / part / f"{TRAIN if 'train' in part else TEST}.npy").read_bytes()
        assert (again / part / f"{TRAIN if 'train' in part else TEST}.npy").read_bytes() == first


def test_aist_rerun_continues_and_frames_limit(tmp_path, models, capsys):
    source, root = tmp_path / "aist", tmp_path / "out"
    aist_download(source)
    argv = ["--data", "aist", "--from", str(source), "--root", str(root), "--frames", "3"]
    argv += ["--body-model", str(models["smpl"])]
    assert prepare(argv) == 0
    first = (root / "test" / "vertices" / f"{TEST}.npy").read_bytes()
    assert load_sequences("aist", "train", root)[0].vertices.shape == (3, POINTS, 3)
    # An interrupted run: no meta.json, one sequence missing. The rerun writes only that one.
    (root / "meta.json").unlink()
    (root / "test" / "vertices" / f"{TEST}.npy").unlink()
    capsys.readouterr()
    assert prepare(argv) == 0
    assert "(1 written, 1 already there)" in capsys.readouterr().out
    assert (root / "test" / "vertices" / f"{TEST}.npy").read_bytes() == first


def hanco_download(root, model_path, unit=1.0):
    """A HanCo folder for HAS_FIT; keypoints (in metres times `unit`) from the posed model."""
    model = body_models.load_model(model_path)
    rng = np.random.default_rng(5)
    (root).mkdir(parents=True)
    (root / "meta.json").write_text(json.dumps({"has_fit": HAS_FIT, "is_valid": HAS_FIT}))
    keypoints = {}
    for sid, fits in enumerate(HAS_FIT):
        for fid, fit in enumerate(fits):
            pose = np.concatenate([rng.normal(size=3), rng.normal(scale=0.2, size=45)])
            shapes = rng.normal(scale=0.5, size=10)
            global_t = np.array([0.3, -0.2, 0.9]) + rng.normal(scale=0.05, size=3)
            full = body_models.mano_pose(model, pose)
            _, joints = body_models.pose_model(model, full, betas=shapes, trans=global_t)
            points = joints[MANO_TO_KEYPOINTS] * unit
            xyz = hanco.frame_file(root, "xyz", sid, fid)
            xyz.parent.mkdir(parents=True, exist_ok=True)
            xyz.write_text(json.dumps(points.tolist()))
            if fit:
                keypoints[sid, fid] = points
                fit_file = hanco.frame_file(root, "shape", sid, fid)
                fit_file.parent.mkdir(parents=True, exist_ok=True)
                content = {
                    "poses": [pose.tolist()],
                    "shapes": [shapes.tolist()],
                    "global_t": [[global_t.tolist()]],
                }
                fit_file.write_text(json.dumps(content))
    return keypoints


def test_hanco_download(tmp_path, models, capsys):
    source, root = tmp_path / "hanco", tmp_path / "out"
    keypoints = hanco_download(source, models["mano"])
    argv = ["--data", "hanco", "--from", str(source), "--root", str(root)]
    assert prepare([*argv, "--body-model", str(models["mano"])]) == 0
    out = capsys.readouterr().out
    assert "1 sequences with fewer than 2 fitted frames, left out: 0002" in out
    frames = {"0000": 3, "0001": 3}  # 0000 has no fit at frame 2; 0002 only one fitted frame
    split = split_by_frames(frames)
    assert json.loads((root / "split.json").read_text()) == split
    meta = json.loads((root / "meta.json").read_text())
    assert meta["frames"] == frames and meta["fewer_than_two_fits"] == ["0002"]
    assert meta["parents"][:5] == [0, 0, 1, 2, 3] and len(meta["joint_names"]) == 21
    loaded = {s.name: s for part in ("train", "test") for s in load_sequences("hanco", part, root)}
    assert set(loaded) == set(frames)
    assert all(p.name.endswith("_joints.npy") for p in root.glob("*/joints/*.npy"))
    kept = {"0000": [0, 1, 3], "0001": [0, 1, 2]}
    for name, seq in loaded.items():
        expected = np.stack([keypoints[int(name), fid] for fid in kept[name]])
        np.testing.assert_allclose(seq.joints, expected, atol=1e-6)
        assert seq.vertices.shape == (3, POINTS, 3)
        # The 16 MANO joints are keypoints; every point is on the box around one of them.
        mano_joints = seq.joints[:, [MANO_TO_KEYPOINTS.index(j) for j in range(16)]]
        check_on_boxes(np.asarray(seq.vertices), mano_joints, MANO_HALF)


def test_hanco_keypoints_in_another_unit_are_refused(tmp_path, models, capsys):
    source, root = tmp_path / "hanco", tmp_path / "out"
    hanco_download(source, models["mano"], unit=1000.0)  # millimetres
    argv = ["--data", "hanco", "--from", str(source), "--root", str(root)]
    assert prepare([*argv, "--body-model", str(models["mano"])]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    assert re.search(r"xyz/0000/00000000\.json: the keypoints do not lie on the hand", err)
    assert "one frame and one unit" in err and not root.exists()


@pytest.mark.parametrize(
    "case, match",
    [
        ("aist-no-model", r"--data aist meshes .* with the SMPL model.*--body-model FILE.*"),
        ("hanco-no-model", r"--data hanco meshes .* MANO model.*mano\.is\.tue\.mpg\.de"),
        ("smpl-for-hanco", r"SMPL \(24 joints\), but --data hanco needs MANO \(16 joints\)"),
        ("mano-for-aist", r"MANO \(16 joints\), but --data aist needs SMPL \(24 joints\)"),
        ("runs-code", r"bad\.pkl: holds a pickled posix\.system; refused"),
        ("bad-motion", rf"{TRAIN}\.pkl: expected smpl_poses \(T, 72\), smpl_trans \(T, 3\)"),
        ("no-meta", r"no meta\.json; expected the HanCo root"),
        ("missing-model", r"--body-model .*nowhere\.pkl: no such file"),
        ("model-for-dfaust", r"--body-model is read for --data aist / hanco only, not dfaust"),
    ],
)
def test_bad_input(tmp_path, models, capsys, case, match):
    aist_root, hanco_root, root = tmp_path / "aist", tmp_path / "hanco", tmp_path / "out"
    aist_download(aist_root)
    hanco_download(hanco_root, models["mano"])
    data, source, model = "aist", aist_root, models["smpl"]
    if case.startswith("hanco") or case in ("smpl-for-hanco", "no-meta"):
        data, source, model = "hanco", hanco_root, models["mano"]
    if case.endswith("no-model"):
        model = None
    if case == "smpl-for-hanco":
        model = models["smpl"]
    if case == "mano-for-aist":
        model = models["mano"]
    if case == "runs-code":
        model = tmp_path / "bad.pkl"
        model.write_bytes(pickle.dumps({"v_template": RunsCode(tmp_path / "ran")}, protocol=2))
    if case == "bad-motion":
        bad = motion(4, 0)
        bad["smpl_trans"] = bad["smpl_trans"][:, :2]
        with open(aist_root / "motions" / f"{TRAIN}.pkl", "wb") as f:
            pickle.dump(bad, f)
    if case == "no-meta":
        (hanco_root / "meta.json").unlink()
    if case == "missing-model":
        model = tmp_path / "nowhere.pkl"
    if case == "model-for-dfaust":
        data = "dfaust"
    argv = ["--data", data, "--from", str(source), "--root", str(root)]
    argv += [] if model is None else ["--body-model", str(model)]
    assert prepare(argv) == 2
    err = capsys.readouterr().err
    assert re.search(match, err) and len(err.strip().splitlines()) == 1
    assert not root.exists() and not (tmp_path / "ran").exists()


class RunsCode:
    """Unpickling this would run a shell command."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        import os

        return (os.system, (f"touch {self.marker}",))


def test_mesh_folders_still_need_no_model(tmp_path):
    """aist / hanco given as mesh folders (the form for any real set) are read as before."""
    import trimesh

    source, root = tmp_path / "meshes", tmp_path / "out"
    for seq in ("a", "b"):
        (source / seq).mkdir(parents=True)
        for t in range(2):
            trimesh.creation.box().export(source / seq / f"{t}.obj")
    assert prepare(["--data", "hanco", "--from", str(source), "--root", str(root)]) == 0
    assert json.loads((root / "meta.json").read_text())["format"] == "mesh-folders"


def test_help_names_the_body_model_downloads(capsys):
    assert nmjax_main(["prepare-data", "--help"]) == 0
    out = capsys.readouterr().out
    for line in (
        "--body-model FILE",
        "nmjax prepare-data --data aist --from AIST_ROOT --body-model SMPL_MALE.pkl",
        "nmjax prepare-data --data hanco --from HANCO_ROOT --body-model MANO_RIGHT.pkl",
        "https://google.github.io/aistplusplus_dataset",
        "https://smpl.is.tue.mpg.de",
        "https://mano.is.tue.mpg.de",
    ):
        assert line in out
