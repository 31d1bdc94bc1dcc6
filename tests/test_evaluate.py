"""Tests of nmjax.evaluate: statistics, M-CD on hand-made cases, and the command on a tiny run."""

from __future__ import annotations

import json
import types

import numpy as np
import pytest
from experiment_scripts import load_experiment
from tiny_runs import PARENTS, make_runs

from nmjax import evaluate, metrics, provenance
from nmjax.data.voxelize import voxelize
from nmjax.tasks import Interpolators
from nmjax.train.trained import Detector

K = len(PARENTS)
SKELETON_KEYS = (
    "joint_distance",
    "joint_coverage_0.05",
    "joint_coverage_0.10",
    "edge_precision",
    "edge_precision_within_2_hops",
    "bone_recall",
    "distinct_nodes",
)
FIELD_KEYS = ("cd_j2j", "cd_j2b", "cd_b2b", "rig_fit_cd", "rig_fit_cd_capture")


def test_confidence_interval_is_the_student_t_half_width():
    # mean 2, sample std 1, n = 3: t_{0.975, 2} / sqrt(3) = 4.302653 / 1.732051
    assert evaluate.confidence_interval([1.0, 2.0, 3.0]) == pytest.approx(2.484138, abs=1e-5)
    assert np.isnan(evaluate.confidence_interval([5.0]))
    summary = evaluate.summarize([1.0, float("nan"), 3.0])
    assert summary["mean"] == 2.0 and summary["n"] == 2


def test_summaries_per_rate_and_their_table():
    per_sequence = {
        "Ours": {3: {"a": 1.0, "b": 3.0}, 5: {"a": 4.0}},
        "Lerp": {3: {"a": 2.0, "b": 2.0}, 5: {"a": float("nan")}},
    }
    summary = evaluate.summarize_per_rate(per_sequence)
    assert list(summary) == ["Ours", "Lerp"] and list(summary["Ours"]) == ["3", "5"]
    assert summary["Ours"]["3"]["mean"] == 2.0 and summary["Ours"]["3"]["n"] == 2
    # sample std sqrt(2), n = 2: t_{0.975, 1} = 12.706205, half-width 12.706205 * sqrt(2 / 2)
    assert summary["Ours"]["3"]["ci95"] == pytest.approx(12.706205, abs=1e-5)
    assert summary["Ours"]["5"]["per_sequence"] == {"a": 4.0}
    assert summary["Lerp"]["5"]["n"] == 0
    lines = evaluate.interpolation_table(summary, "M-CD")
    assert lines[:4] == [
        "## M-CD",
        "",
        "| model | SR = 3 | SR = 5 | Average |",
        "|---|---|---|---|",
    ]
    assert lines[4] == "| Ours | 2 (12.7) | 4 (n/a) | 3 |"
    assert lines[5] == "| Lerp | 2 (0) | n/a | 2 |"  # NaN left out of the average
    assert lines[6:] == [""] and evaluate.interpolation_table({}, "M-CD") == []


def test_keyframe_starts_fit_inside_the_sequence():
    np.testing.assert_array_equal(evaluate.keyframe_starts(12, 3, 10), [0, 3, 6])
    np.testing.assert_array_equal(evaluate.keyframe_starts(12, 5, 10), [0, 5])
    assert len(evaluate.keyframe_starts(12, 12, 10)) == 0
    assert list(evaluate.keyframe_starts(100, 3, 2)) == [0, 96]


def test_identical_sequences_have_zero_motion_chamfer():
    rng = np.random.default_rng(0)
    v = (rng.random((4, 8, 8, 8)) > 0.7).astype(np.float32)
    assert metrics.motion_chamfer(v, v) == pytest.approx(0.0, abs=1e-6)  # float32 round-off
    assert metrics.motion_chamfer(v, v[::-1]) > 0.0


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return make_runs(tmp_path_factory.mktemp("tiny-eval"))


def test_lerp_of_a_linear_motion_scores_zero_and_a_curved_one_does_not(runs, monkeypatch):
    """M-CD pipeline with a stand-in decoder that voxelises the keypoints themselves."""
    from nmjax import run_folder
    from nmjax.config import SkelTrainConfig
    from nmjax.data.datasets import load_sequences

    cfg = run_folder.load_config(runs["skel"], SkelTrainConfig)
    grid = cfg.data.grid
    (seq,) = load_sequences(cfg.data.name, "test", cfg.data.root)
    t = np.arange(12, dtype=np.float32)[:, None, None]
    start = np.random.default_rng(1).uniform(-0.8, 0.0, (1, K, 3)).astype(np.float32)
    linear = np.concatenate([start + 0.06 * t, np.ones((12, K, 1), np.float32)], axis=-1)
    curved = linear.copy()
    curved[..., 2] += 0.5 * np.sin(t[..., 0] * 0.9)

    def decode(keypoints, first_voxels):
        return voxelize(keypoints[..., :3], grid)

    detector = types.SimpleNamespace(cfg=cfg, run=runs["skel"], decode=decode)
    interp = Interpolators(nm=None, vrnn=None, trajectories=1)
    for traj, zero in ((linear, True), (curved, False)):
        monkeypatch.setattr(
            "nmjax.train.trained.sequence_voxels",
            lambda *a, traj=traj: voxelize(traj[..., :3], grid),
        )
        tables = evaluate.evaluate_interpolation(
            detector, interp, {seq.name: traj}, rates=(3, 5), methods=("Lerp",)
        )
        out, errors = tables["interpolation"], tables["interpolation_keypoints"]
        kp_means = [errors["Lerp"][r]["mean"] for r in ("3", "5")]
        assert kp_means == pytest.approx([0.0, 0.0], abs=1e-9) if zero else min(kp_means) > 1e-3
        assert set(out) == {"Lerp"} and set(out["Lerp"]) == {"3", "5"}
        means = [out["Lerp"][r]["mean"] for r in ("3", "5")]
        if zero:
            assert means == pytest.approx([0.0, 0.0], abs=1e-3)  # x1e3, float32 round-off
        else:
            assert min(means) > 1.0  # whole cells apart: (2 / 16)^2 x 1e3 = 15.6 per cell


def test_evaluate_command_writes_all_tables(runs, tmp_path):
    from nmjax import cli

    out = tmp_path / "eval"
    argv = ["evaluate", "--run", str(runs["nm"]), "--rates", "3,5", "--trajectories", "2"]
    assert cli.main([*argv, "--max-segments", "1", "--max-crops", "1", "--out", str(out)]) == 0
    results = json.loads((out / "results.json").read_text())
    assert results["vrnn_run"] == str(runs["vrnn"])  # found beside the nm run
    stamp = results["provenance"]  # the commit, machine and every measure's definition
    assert {"sc", "tracking", "joint_distance", "interpolation"} <= set(stamp["metrics"])
    assert provenance.read_png(out / "mcd.png") == stamp
    p1 = results["phase1"]
    assert 0.0 < p1["sc"]["score"] <= 1.0 and 0.0 < p1["sc_fixed_nodes"]["score"] <= 1.0
    assert np.isfinite(p1["tracking"]["mean"])
    bones = p1["bone_length_variation"]
    assert np.isfinite(bones["mean"]) and bones["mean"] >= 0 and bones["kept_nodes"] >= 1
    for key in SKELETON_KEYS:
        assert key in p1, key
    assert 0.0 < p1["joint_distance"]["mean"] < 2 * np.sqrt(3) and p1["joint_distance"]["n"] == 1
    assert 1 <= p1["distinct_nodes"] <= p1["skeleton_kept_nodes"] == K
    # The field's scores: the six kept nodes' tree against synth-arm's 13-joint tree, the
    # skeleton chamfers and the rig's fit error, each defined in the stamp.
    assert isinstance(p1["tree_edit_distance"], int) and p1["tree_edit_distance"] >= 13 - K
    for key in FIELD_KEYS:
        assert np.isfinite(p1[key]["mean"]) and p1[key]["mean"] >= 0 and p1[key]["n"] == 1, key
        assert key in stamp["metrics"], key
    assert set(results["interpolation"]) == {"Ours", "VRNN", "Lerp", "Slerp"}
    for by_rate in results["interpolation"].values():
        assert all(np.isfinite(by_rate[r]["mean"]) and by_rate[r]["n"] == 1 for r in ("3", "5"))
    tables = (out / "tables.md").read_text()
    for row in (
        "| Ours |",
        "| VRNN |",
        "| Lerp |",
        "| Slerp |",
        "SR = 5",
        "fixed node set",
        "Skeleton against the ground truth",
        "bone recall",
        "## The field's scores",
        "CD-B2B x1e-2",
        "## Provenance",
    ):
        assert row in tables
    assert (out / "mcd.png").stat().st_size > 0


def test_evaluate_of_a_phase1_run_takes_the_kept_nodes_stored_in_its_skeleton(
    runs, tmp_path, capsys
):
    """`nmjax evaluate --run SKEL_RUN`: the skeleton measures and the bone-length variation in
    results.json and tables.md, on the nodes and tree skeleton.json keeps (not a new pruning of
    its intensities)."""
    import shutil

    from nmjax import cli

    run = tmp_path / "skel"
    shutil.copytree(runs["skel"], run)
    path = run / "skeleton.json"
    stored = json.loads(path.read_text())
    # Keep only keypoints 0, 1 and 2 (the chain 0 - 1 - 2); 3, 4, 5 re-attached to 2, 1, 1.
    stored.update(keep=[True, True, True, False, False, False], pruned_parents=[0, 0, 1, 2, 1, 1])
    path.write_text(json.dumps(stored))
    out = tmp_path / "eval"
    assert cli.main(["evaluate", "--run", str(run), "--max-crops", "1", "--out", str(out)]) == 0
    results = json.loads((out / "results.json").read_text())
    assert "interpolation" not in results["provenance"]["metrics"]  # phase 1 only
    p1 = results["phase1"]
    assert p1["skeleton_kept_nodes"] == 3 and p1["bone_length_variation"]["kept_nodes"] == 3
    assert 1 <= p1["distinct_nodes"] <= 3
    for key in SKELETON_KEYS[1:-1]:
        assert 0.0 <= p1[key] <= 1.0, key
    assert p1["edge_precision"] <= p1["edge_precision_within_2_hops"]
    # The joint distance is the one of the stored node set, recomputed from the same crops.
    det = Detector.load(run)
    (name, _, joints, keypoints, _), *rest = evaluate.phase1_outputs(det, max_crops=1)
    assert not rest  # one test sequence
    expected = float(metrics.joint_distance(keypoints, joints, np.array(stored["keep"])))
    assert p1["joint_distance"]["per_sequence"] == {name: pytest.approx(expected, rel=1e-6)}
    assert p1["joint_distance"]["mean"] == pytest.approx(expected, rel=1e-6)
    # The bones between the stored kept nodes of the stored pruned tree: 1 - 0 and 2 - 1 only.
    parents, keep = np.array(stored["pruned_parents"]), np.array(stored["keep"])
    bones = float(metrics.bone_length_variation(keypoints, parents, kept=keep))
    chain = float(metrics.bone_length_variation(keypoints[..., :3, :], np.array([0, 0, 1]), 0.0))
    assert p1["bone_length_variation"]["mean"] == pytest.approx(bones, rel=1e-6)
    assert bones == pytest.approx(chain, rel=1e-6)
    # The kept chain of 3 nodes against synth-arm's 13-joint tree (a chain 0-...-8 that forks
    # into 9-10 and 11-12): deleting the 10 nodes it lacks leaves a chain of 3, and no script
    # with fewer edits removes 10 nodes: TED = 10.
    assert p1["tree_edit_distance"] == 10
    # CD-J2J over the stored kept nodes: the same as the three kept keypoints on their own.
    crops = next(evaluate.phase1_crops(det, max_crops=1))
    kept_xyz = crops["keypoints"][..., :3][..., keep, :]
    own = metrics.cd_j2j(
        metrics.unit_box(kept_xyz, crops["points"]), metrics.unit_box(joints, crops["points"])
    )
    expected = float(np.mean(own)) * metrics.SKELETON_CD_SCALE
    assert p1["cd_j2j"]["per_sequence"] == {name: pytest.approx(expected, rel=1e-5)}
    # The fit error of the rig `nmjax export` builds on the three kept nodes.
    (fit,) = [
        evaluate.crop_fit_error(kp, pts, float(s), (parents, keep), 30.0)
        for kp, pts, s in zip(crops["keypoints"], crops["points"], crops["box_scale"], strict=True)
    ]
    assert p1["rig_fit_cd"]["mean"] == pytest.approx(fit["cd"], rel=1e-5)
    assert p1["rig_fit_cd_capture"]["mean"] == pytest.approx(fit["cd_capture"], rel=1e-5)
    scores = evaluate.phase1_scores(p1)
    assert scores["tree_edit_distance"] == 10
    for key in FIELD_KEYS:
        assert scores[key] == p1[key]["mean"] and f"{key}_ci95" in scores, key
    tables = (out / "tables.md").read_text()
    assert "## Skeleton against the ground truth" in tables and " / 3 |" in tables
    assert "| Ours | 10 |" in tables
    # A skeleton.json without the kept nodes is refused with the command that rewrites it.
    del stored["keep"]
    path.write_text(json.dumps(stored))
    capsys.readouterr()
    assert cli.main(["evaluate", "--run", str(run), "--max-crops", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "lacks `keep`" in err and "nmjax extract-skeleton --run" in err


def test_skeleton_against_truth_without_a_true_tree_and_its_table():
    """Without meta.json parents only the tree-blind measures are reported; the table says n/a."""
    gt = np.float32([[0, 0, 0], [0.3, 0, 0], [0.6, 0, 0]])[None, None]  # (C=1, T=1, J=3, 3)
    kp = np.concatenate([gt, np.ones((1, 1, 3, 1), np.float32)], -1)
    seqs = [gt, gt + np.float32(0.01)]
    keypoints = [kp, kp]
    skeleton = (np.array([0, 0, 1]), np.ones(3, bool))
    out = evaluate.skeleton_against_truth(keypoints, seqs, skeleton, None, ["a", "b"])
    assert "edge_precision" not in out and "bone_recall" not in out
    assert out["joint_distance"]["per_sequence"]["a"] == 0.0
    assert out["joint_distance"]["mean"] == pytest.approx(np.sqrt(3) * 0.01 / 2, rel=1e-5)
    assert out["joint_distance"]["n"] == 2 and out["distinct_nodes"] == 3
    assert out["joint_coverage_0.05"] == 1.0 and out["skeleton_kept_nodes"] == 3
    full = evaluate.skeleton_against_truth(
        keypoints, seqs, skeleton, np.array([0, 0, 1]), ["a", "b"]
    )
    assert full["edge_precision"] == 1.0 and full["bone_recall"] == 1.0
    lines = evaluate.skeleton_truth_table(
        {"Ours": out, "Full": {**full, "sc": {"score": 0.5}}}, sc=True
    )
    assert lines[0].startswith("| model | SC | SC fixed nodes | joint distance")
    assert lines[2].split(" | ")[1:3] == ["n/a", "n/a"] and "| n/a | n/a | n/a |" in lines[2]
    assert lines[3].startswith("| Full | 0.5 | n/a | 0.00866 (0.11) |")
    assert lines[3].endswith("| 1 | 1 | 1 | 3 / 3 |")
    assert evaluate.skeleton_truth_table({"Ours": {"sc": {"score": 0.5}}}) == []


def test_the_rig_reproduces_a_capture_that_is_its_own_skinning_and_not_another_one():
    """`crop_fit_error`: the rig `nmjax export` builds from keypoints, skinned by Algorithm 2 on
    frame 0, fits frames that are exactly that skinning (0) and not a capture that moves
    otherwise."""
    rng = np.random.default_rng(0)
    parents, keep = np.array([0, 0, 1, 2, 1]), np.array([True, True, True, False, True])
    rest = np.float32([[0, 0, 0], [0.3, 0, 0], [0.6, 0, 0], [0.8, 0, 0], [0.3, 0.3, 0]])
    frames = 5
    angle = np.linspace(0, 0.6, frames)
    keypoints = np.ones((frames, 5, 4), np.float32)
    keypoints[..., :3] = rest
    # Joint 2 (and the pruned 3 beyond it) swings about z around joint 1; joint 4 is still.
    turn = np.stack([np.cos(angle), np.sin(angle), np.zeros(frames)], -1)
    keypoints[:, 2, :3] = rest[1] + 0.3 * turn
    keypoints[:, 3, :3] = rest[1] + 0.5 * turn
    surface = rng.uniform([-0.1, -0.1, -0.1], [0.7, 0.4, 0.1], (300, 3)).astype(np.float32)
    rig, weights = evaluate.crop_rig(keypoints, surface, (parents, keep), 30.0)
    np.testing.assert_array_equal(rig.joints, [0, 1, 2, 4])  # the kept nodes, parents first
    assert weights.shape == (300, 4) and np.allclose(weights.sum(1), 1.0, atol=1e-6)
    skinned = evaluate.skinned_surface(rig, surface, weights)
    assert skinned.shape == (frames, 300, 3)
    np.testing.assert_allclose(skinned[0], surface, atol=1e-6)  # frame 0 is the rest pose
    assert np.abs(skinned[-1] - surface).max() > 0.1  # and the swinging bone's points move
    fit = evaluate.crop_fit_error(keypoints, skinned, 2.0, (parents, keep), 30.0)
    assert fit["cd"] == pytest.approx(0.0, abs=1e-3) and fit["cd_capture"] < 1e-7
    # The capture shifted by 0.05 from frame 1 on: the rig, driven by the same keypoints, stays.
    shifted = skinned.copy()
    shifted[1:] += np.float32([0.0, 0.05, 0.0])
    fit = evaluate.crop_fit_error(keypoints, shifted, 2.0, (parents, keep), 30.0)
    assert fit["cd"] > 1.0 and fit["cd_capture"] == pytest.approx(fit["cd"] / 1e4 / 4, rel=1e-6)
    # Larger crops are compared on a fixed subset of point indices, the same in every frame.
    np.testing.assert_array_equal(evaluate.fit_subset(300), np.arange(300))
    subset = evaluate.fit_subset(5000)
    assert len(np.unique(subset)) == evaluate.FIT_POINTS and np.all(np.diff(subset) > 0)
    np.testing.assert_array_equal(evaluate.fit_subset(5000), subset)
    fewer = evaluate.crop_fit_error(keypoints, shifted, 2.0, (parents, keep), 30.0, limit=100)
    pick = evaluate.fit_subset(300, 100)
    rig, weights = evaluate.crop_rig(keypoints, shifted[0, pick], (parents, keep), 30.0)
    direct = metrics.rig_fit_error(
        evaluate.skinned_surface(rig, shifted[0, pick], weights), shifted[:, pick], 2.0
    )
    assert fewer == pytest.approx(direct, rel=1e-6)


def test_the_field_scores_table_says_n_a_where_a_score_is_missing():
    full = {
        "tree_edit_distance": 4,
        **{k: {"mean": 1.5, "ci95": 0.25} for k in FIELD_KEYS},
    }
    lines = evaluate.rig_scores_table({"Ours": full, "No joints": {"rig_fit_cd": full["cd_j2j"]}})
    assert lines[0].startswith("| model | TED | CD-J2J x1e-2 | CD-J2B x1e-2 | CD-B2B x1e-2 |")
    assert lines[2] == "| Ours | 4 | " + " | ".join(["1.5 (0.25)"] * 5) + " |"
    assert lines[3] == "| No joints | n/a | n/a | n/a | n/a | 1.5 (0.25) | n/a |"
    assert evaluate.rig_scores_table({"Ours": {"sc": {"score": 0.5}}}) == []


def test_evaluate_refuses_a_vrnn_run_and_a_missing_folder(runs, tmp_path, capsys):
    from nmjax import cli

    assert cli.main(["evaluate", "--run", str(runs["vrnn"])]) == 2
    assert "--vrnn-run" in capsys.readouterr().err
    assert cli.main(["evaluate", "--run", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err
    assert "config.json not found" in err and len(err.strip().splitlines()) == 1


def test_ground_truth_supervised_variant_replaces_only_the_volume_term():
    """Table 2's GT baseline: weights.vol_target="joints" swaps L_vol for the joint MSE."""
    import dataclasses

    import jax.numpy as jnp

    from nmjax import losses
    from nmjax.config import LossWeights

    rng = np.random.default_rng(0)
    b, t, g, k = 1, 3, 8, 4
    outputs = {
        "voxels": jnp.asarray((rng.random((b, t, 2 * g, 2 * g, 2 * g)) > 0.8), jnp.float32),
        "recon": jnp.full((b, t, 2 * g, 2 * g, 2 * g), 0.5),
        "heatmaps": jnp.asarray(rng.random((b, t, g // 2, g // 2, g // 2, k)), jnp.float32),
        "keypoints": jnp.asarray(rng.uniform(0, 1, (b, t, k, 4)), jnp.float32),
        "affinity": losses.affinity_from_params(jnp.ones((2, k, k - 1))),
        "joints": jnp.asarray(rng.uniform(0, 1, (b, t, k, 3)), jnp.float32),
    }
    weights = LossWeights()
    gt = dataclasses.replace(weights, vol_target="joints")
    _, terms = losses.skeleton_loss(outputs, weights)
    _, gt_terms = losses.skeleton_loss(outputs, gt)
    kp, joints = np.asarray(outputs["keypoints"]), np.asarray(outputs["joints"])
    expect = np.mean(np.sum((kp[..., :3] - joints) ** 2, axis=-1))
    assert float(gt_terms["vol"]) == pytest.approx(expect, rel=1e-5)
    assert float(terms["vol"]) != pytest.approx(expect, rel=1e-3)
    for name in ("recon", "sparse", "sep", "local", "time", "complex", "traj"):
        assert float(gt_terms[name]) == float(terms[name])
    with pytest.raises(ValueError, match="model.num_keypoints=5"):
        losses.skeleton_loss({**outputs, "joints": outputs["joints"][..., :1, :].repeat(5, -2)}, gt)
    with pytest.raises(ValueError, match="vol_target"):
        losses.skeleton_loss(outputs, dataclasses.replace(weights, vol_target="bones"))
    without = {key: v for key, v in outputs.items() if key != "joints"}
    with pytest.raises(ValueError, match="ground-truth joints"):
        losses.skeleton_loss(without, gt)


# --- generation ---------------------------------------------------------------------------------


def rigid_motion(frames: int, k: int = K, seed: int = 0) -> np.ndarray:
    """(frames, K, 4) keypoints of one rest pose rotated about z and translated frame by frame."""
    rng = np.random.default_rng(seed)
    rest = rng.normal(size=(k, 3))
    angle = np.linspace(0.0, 2.0, frames)
    c, s = np.cos(angle), np.sin(angle)
    rot = np.stack(
        [
            np.stack([c, -s, 0 * c], -1),
            np.stack([s, c, 0 * c], -1),
            np.tile([0, 0, 1.0], (frames, 1)),
        ],
        axis=-2,
    )  # (frames, 3, 3)
    mu = np.einsum("tij,kj->tki", rot, rest) + np.linspace(0, 1, frames)[:, None, None]
    return np.concatenate([mu, np.full((frames, k, 1), 0.7)], axis=-1).astype(np.float32)


def test_conditioning_and_real_clips_fit_inside_the_sequences():
    traj = {"a": rigid_motion(12), "b": rigid_motion(30, seed=1)}
    names, x_cond = evaluate.conditioning_clips(traj, cond=5, per_sequence=3)
    assert names == [("a", 0), ("a", 3), ("a", 7), ("b", 0), ("b", 12), ("b", 25)]
    assert x_cond.shape == (6, 5, K, 4)
    np.testing.assert_array_equal(x_cond[2], traj["a"][7:12])
    real = evaluate.real_clips(traj, frames=20, stride=5, per_sequence=16)
    assert real.shape == (3, 20, K, 4)  # only "b" is long enough: starts 0, 5, 10
    np.testing.assert_array_equal(real[2], traj["b"][10:30])
    assert evaluate.real_clips(traj, frames=31, stride=5, per_sequence=16).shape == (0, 31, K, 4)
    with pytest.raises(ValueError, match="lower --cond"):
        evaluate.conditioning_clips(traj, cond=40, per_sequence=3)


def test_generation_measures_of_rigid_held_and_stretched_motion():
    parents, kept = np.array(PARENTS), np.ones(K, bool)
    x_cond = rigid_motion(8)[None, :5]  # (B=1, 5, K, 4)
    real = rigid_motion(8)[None]
    # Held pose: its samples are identical and no bone changes length.
    held = evaluate.hold_last_pose(x_cond, 8, samples=3)
    assert held.shape == (1, 3, 8, K, 4)
    out = evaluate.generation_measures(held, real, parents, kept, root=0)
    assert out["diversity"]["mean"] == 0.0 and out["bone_error"]["mean"] < 1e-6
    assert out["set_distance"]["mean"] > 0.0  # the real clip moves, the held one does not
    # A rigid motion in every sample: bone-length error 0; the real clip itself: set distance 0.
    same = np.broadcast_to(real[:, None], (1, 2, 8, K, 4))
    out = evaluate.generation_measures(same, real, parents, kept, root=0)
    assert out["bone_error"]["mean"] == pytest.approx(0.0, abs=1e-5)
    assert out["set_distance"]["mean"] == pytest.approx(0.0, abs=1e-6)
    assert out["set_distance"]["to_real"]["n"] == 1
    # Bones that stretch over time do not score 0, and the faint intensities of a model do not
    # change which bones count: the run's node mask does.
    stretched = same.copy()
    stretched[..., :3] *= np.linspace(1.0, 2.0, 8)[:, None, None]
    stretched[..., 3] = 0.0
    out = evaluate.generation_measures(stretched, real[:0], parents, kept, root=0, no_real="x")
    assert out["bone_error"]["mean"] > 0.05
    assert np.isnan(out["set_distance"]["mean"]) and out["set_distance"]["reason"] == "x"


def test_generation_command_writes_its_table_and_plot(runs, tmp_path):
    from nmjax import cli

    out = tmp_path / "eval"
    argv = ["evaluate", "--run", str(runs["nm"]), "--vrnn-run", str(runs["vrnn"]), "--generation"]
    argv += ["--horizons", "3,20", "--samples", "2", "--cond", "2", "--clips", "2"]
    assert cli.main([*argv, "--out", str(out)]) == 0
    results = json.loads((out / "generation.json").read_text())
    assert set(results["methods"]) == {"Ours", "VRNN", "Hold last pose"}
    assert len(results["clips"]) == 2  # one 12-frame test sequence, two conditioning clips
    ours, vrnn, hold = (results["methods"][m] for m in ("Ours", "VRNN", "Hold last pose"))
    assert ours["3"]["bone_error"]["mean"] < 1e-5  # forward kinematics keeps every bone
    assert vrnn["3"]["bone_error"]["mean"] > 1e-3  # the untrained positional decoder does not
    assert hold["3"]["diversity"]["mean"] == 0.0 and ours["3"]["diversity"]["mean"] > 0.0
    assert ours["3"]["diversity"]["n"] == 2 and np.isfinite(ours["3"]["set_distance"]["mean"])
    # No 20-frame test clip exists: the set distance is n/a with the reason, the rest measured.
    assert "12" in ours["20"]["set_distance"]["reason"] and ours["20"]["set_distance"]["n"] == 0
    assert np.isfinite(ours["20"]["set_diversity"]["mean"])
    table = (out / "generation.md").read_text()
    for text in ("| Ours |", "| VRNN |", "| Hold last pose |", "N = 20", "no test sequence has 20"):
        assert text in table
    assert "## Provenance" in table and "  - `bone_error`: " in table
    assert provenance.read_png(out / "generation.png") == results["provenance"]
    assert not (out / "results.json").exists()  # the other tables are not recomputed
    # Real clips from longer sequences (--real-keypoints) measure the set distance at N = 20.
    with np.load(runs["skel"] / "keypoints_test.npz") as npz:
        longer = {name: np.concatenate([npz[name]] * 3) for name in npz.files}  # 36 frames
    np.savez(tmp_path / "long.npz", **longer)
    argv += ["--real-keypoints", str(tmp_path / "long.npz")]
    assert cli.main([*argv, "--out", str(tmp_path / "eval2")]) == 0
    results = json.loads((tmp_path / "eval2" / "generation.json").read_text())
    assert results["settings"]["real_keypoints"] == str(tmp_path / "long.npz")
    ours = results["methods"]["Ours"]
    assert np.isfinite(ours["20"]["set_distance"]["mean"]) and ours["20"]["set_distance"]["n"] > 0
    assert cli.main([*argv[:-1], str(tmp_path / "missing.npz")]) == 2


def test_generation_refuses_a_baseline_of_another_skeleton_and_bad_horizons(runs, tmp_path, capsys):
    from nmjax import cli

    other = tmp_path / "dyn-vrnn-other"
    other.mkdir()
    config = json.loads((runs["vrnn"] / "config.json").read_text())
    config["skel_run"] = str(tmp_path / "skel-other")
    (other / "config.json").write_text(json.dumps(config))
    argv = ["evaluate", "--run", str(runs["nm"]), "--generation"]
    assert cli.main([*argv, "--vrnn-run", str(other)]) == 2
    assert "skel-other" in capsys.readouterr().err
    assert cli.main([*argv, "--horizons", "1,5"]) == 2
    assert "--horizons must be comma-separated integers >= 2" in capsys.readouterr().err
    assert cli.main(["evaluate", "--run", str(runs["skel"]), "--generation"]) == 2
    assert "phase-2" in capsys.readouterr().err


def test_train_skel_curves_reports_the_test_scores(runs, tmp_path):
    """experiments/train_skel_curves.py writes the run's test-split scores under "test"."""
    import shutil

    run = tmp_path / "skel"
    shutil.copytree(runs["skel"], run)
    records = [{"step": 5, "train/loss": 2.0}, {"step": 10, "train/loss": 1.5, "val/loss": 1.7}]
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    module = load_experiment("train_skel_curves.py")
    out = tmp_path / "out"
    module.main(["--run", str(run), "--out", str(out), "--max-crops", "1"])
    summary = json.loads((out / "train_skel_synth-arm.json").read_text())
    assert summary["steps"] == 10 and summary["final_val"] == {"loss": 1.7}
    expected = evaluate.evaluate_phase1(Detector.load(run), 1)
    assert summary["test"] == pytest.approx(
        {
            "sc": expected["sc"]["score"],
            "sc_std_over_joints": expected["sc"]["std_over_joints"],
            "sc_fixed_nodes": expected["sc_fixed_nodes"]["score"],
            "sc_fixed_nodes_std_over_joints": expected["sc_fixed_nodes"]["std_over_joints"],
            "tracking_cd": expected["tracking"]["mean"],
            "tracking_cd_ci95": expected["tracking"]["ci95"],
            "bone_length_variation": expected["bone_length_variation"]["mean"],
            "joint_distance": expected["joint_distance"]["mean"],
            "joint_distance_ci95": expected["joint_distance"]["ci95"],
            "skeleton_kept_nodes": expected["skeleton_kept_nodes"],
            **{key: expected[key] for key in SKELETON_KEYS[1:]},
            "tree_edit_distance": expected["tree_edit_distance"],
            **{key: expected[key]["mean"] for key in FIELD_KEYS},
            **{f"{key}_ci95": expected[key]["ci95"] for key in FIELD_KEYS},
        },
        nan_ok=True,  # one test sequence: no CI
    )
    assert (out / "train_skel_synth-arm.png").read_bytes()[:4] == b"\x89PNG"
    assert provenance.read_png(out / "train_skel_synth-arm.png") == summary["provenance"]
    assert summary["provenance"]["metrics"]["test.sc"] == evaluate.PHASE1_METRICS["sc"]
    module.main(["--run", str(run), "--out", str(out), "--no-test"])
    assert "test" not in json.loads((out / "train_skel_synth-arm.json").read_text())
