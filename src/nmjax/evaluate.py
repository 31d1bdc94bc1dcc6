"""`nmjax evaluate --run RUN`: the paper's quantitative tables on the test split.

    nmjax evaluate --run runs/dyn-synth-hand-nm-... [--vrnn-run runs/dyn-...-vrnn-...] [--out DIR]
    nmjax evaluate --run runs/skel-synth-hand-...      (phase-1 metrics only)

- SC-score (Eq. 21, Table 1) and its standard deviation over ground-truth joints, on test crops
  of T frames (each crop normalised on its own, as in training), in the published definition
  ("sc": in each frame keypoints with alpha < 0.2 are no candidates) and with the fixed node set
  of the pruned skeleton ("sc_fixed_nodes").
- Bone-length variation of the pruned skeleton over the same crops (std / mean length per bone).
- The skeleton against the ground truth, on data with joints (DESIGN §9; the kept nodes and
  pruned tree stored in the run's skeleton.json, the true tree from the dataset's meta.json):
  joint distance (mean and 95% CI over test sequences), joint coverage at radius 0.05 and 0.10,
  edge precision (and within two hops), bone recall and distinct nodes (`metrics`).
- 4D-tracking Chamfer x1e4 (Table 2): reconstruction of every crop thresholded at 0.5 against its
  voxels, averaged per sequence; mean and 95% confidence interval over test sequences.
- Interpolation M-CD (Eq. 22, Tables 11-12) at sampling rates SR = 3, 5, ..., 30 for Ours (the
  "nm" dynamics), VRNN (a positional "vrnn" run on the same phase-1 run, when one is given or
  found next to RUN), Lerp and Slerp. Keyframes x_ts, x_te = x_{ts+SR} are taken every SR frames
  of each test sequence, as the phase-2 run was fed (its `inputs`): "crop", each clip ts..te (at
  least T frames) normalised with its own bounding box and run through the detector;
  "sequence", cut from the whole sequence normalised with one box (keypoints_test.npz). Each
  method's keypoints are turned into voxels by the phase-1 decoder (gaussian maps of the
  keypoints + the features of frame ts, Eq. 7) thresholded at 0.5 and compared with the true
  voxels of the same clip on difference voxels. Reported x1e3 (the paper does not state its
  scale); mean and 95% confidence interval over test sequences.

Writes `<out>/results.json`, `<out>/tables.md` and `<out>/mcd.png` (default out: `<run>/eval`),
each stamped with the commit, machine and metric definitions (`nmjax.provenance`).

    nmjax evaluate --run RUN [--vrnn-run RUN2] --generation [--horizons 25,100,300] [--samples 10]

evaluates generation instead (beyond the paper, which shows it only as pictures): on conditioning
clips of T_cond test frames (on "crop" inputs detected as the release's generation does, the
first T_cond frames of the clip's first crop normalised on its own), S futures per clip from Ours,
VRNN and the hold-last-pose baseline,
at each horizon N (generated frames) the diversity (average pairwise distance of the S samples,
and of the generated set as a whole), the bone-length error of the generated frames
(`metrics.bone_length_variation` on the pruned skeleton) and the set distance to the real test
clips of N frames (`metrics.set_distance`), with 95% confidence intervals over clips. Writes
`<out>/generation.json`, `generation.md` and `generation.png` (each measure against N).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from nmjax import atomic, metrics, provenance, runs, tasks
from nmjax.data.datasets import pad_with_last
from nmjax.runs import Detector
from nmjax.tasks import Interpolators

SAMPLING_RATES = (3, 5, 10, 15, 20, 25, 30)
METHODS = ("Ours", "VRNN", "Lerp", "Slerp")
MCD_SCALE = 1e3
# One line per measure of results.json, recorded in every results file (`nmjax.provenance`).
PHASE1_METRICS = {
    "sc": "SC-score, Eq. 21 as published: in each frame keypoints with alpha < 0.2 are no "
    "candidates for a joint's nearest keypoint; counts over all test frames (Table 1)",
    "sc_fixed_nodes": "Eq. 21 over the fixed node set of the pruned skeleton in every frame",
    "tracking": "4D-tracking Chamfer x1e4 (Table 2): reconstruction thresholded at 0.5 against "
    "the crop's voxels, mean per sequence; mean and 95% CI over test sequences",
    "bone_length_variation": "std / mean of each bone's length of the pruned skeleton over a "
    "crop of T frames, mean over bones and crops",
    "joint_distance": "mean distance from a ground-truth joint to its nearest kept node (cube "
    "[-1, 1]^3), mean over joints and frames per sequence; mean and 95% CI over sequences",
    "joint_coverage_0.05, joint_coverage_0.10": "share of joint-frames with a kept node within "
    "0.05 (0.10)",
    "edge_precision": "share of skeleton edges whose nodes' joints are the same or adjacent in "
    f"the true tree (edge_precision_within_{metrics.TWO_HOPS}_hops: within two hops)",
    "bone_recall": "share of true bones whose joints' nodes are the same or adjacent in the "
    "skeleton",
    "distinct_nodes": "kept nodes that are some joint's most frequent nearest kept node",
}
INTERPOLATION_METRICS = {
    "interpolation": "M-CD (Eq. 22) x1e3, Tables 11-12: keypoints between keyframes SR frames "
    "apart decoded to voxels (phase-1 decoder, threshold 0.5), compared with the true voxels "
    "on difference voxels; mean and 95% CI over test sequences",
    "interpolation_keypoints": "squared xyz error of the in-between keypoints against the "
    "detector's, summed over K, mean over frames; mean and 95% CI over test sequences",
}


# --- statistics -------------------------------------------------------------------------------


def confidence_interval(values: np.ndarray | list[float], level: float = 0.95) -> float:
    """Half-width of the Student-t confidence interval of the mean (NaN for fewer than 2 values)."""
    from scipy import stats

    x = np.asarray([v for v in np.asarray(values, np.float64).ravel() if np.isfinite(v)])
    if len(x) < 2:
        return float("nan")
    sem = float(np.std(x, ddof=1)) / math.sqrt(len(x))
    return float(stats.t.ppf(0.5 + level / 2, len(x) - 1) * sem)


def summarize(values: list[float]) -> dict[str, float]:
    """{"mean", "ci95", "n"} of the finite values."""
    x = np.asarray([v for v in values if np.isfinite(v)], np.float64)
    mean = float(np.mean(x)) if len(x) else float("nan")
    return {"mean": mean, "ci95": confidence_interval(x), "n": int(len(x))}


# --- runs ---------------------------------------------------------------------------------------


# --- phase 1: SC-score and 4D tracking --------------------------------------------------------


def test_crops(seq, frames: int, sample_rate: int, grid: int, max_crops: int):
    """Non-overlapping crops of one sequence, each normalised and voxelised like training crops.

    Returns:
      voxels (C, T, G, G, G) and joints (C, T, J, 3) (None when the sequence has none).
    """
    from nmjax.data.datasets import crop_sequence, crop_span
    from nmjax.data.voxelize import normalize_sequence, voxelize

    span = crop_span(frames, sample_rate)
    starts = np.arange(0, max(seq.num_frames - span, 0) + 1, span)
    if len(starts) > max_crops:
        starts = starts[np.linspace(0, len(starts) - 1, max_crops).astype(int)]
    voxels, joints = [], []
    for start in starts:
        points, gt = crop_sequence(seq, frames, sample_rate, int(start))
        points, gt = normalize_sequence(points, gt)
        voxels.append(voxelize(points, grid))
        joints.append(gt)
    has_joints = all(j is not None for j in joints)
    return np.stack(voxels), (np.stack(joints) if has_joints else None)


def phase1_outputs(detector: Detector, max_crops: int = 8, split: str = "test"):
    """The detector on the crops of `test_crops`, one sequence of `split` at a time.

    Yields:
      (sequence name, voxels (C, T, G, G, G), joints (C, T, J, 3) or None, keypoints
      (C, T, K, 4), reconstructions (C, T, G, G, G)).
    """
    from nmjax.data.datasets import load_sequences

    cfg = detector.cfg
    for seq in load_sequences(cfg.data.name, split, cfg.data.root):
        voxels, joints = test_crops(
            seq, cfg.data.frames, cfg.data.sample_rate, cfg.data.grid, max_crops
        )
        keypoints, recon = detector.run_batches(voxels)
        yield seq.name, voxels, joints, keypoints, recon


def true_tree(detector: Detector, num_joints: int) -> np.ndarray | None:
    """The ground-truth kinematic tree of the detector's dataset: the `parents` of its meta.json
    (read by `layout.read_meta`, which takes the root in any convention and returns it as its own
    parent), or None when the dataset does not record them.

    Raises:
      ValueError: the recorded parents are not a tree over the `num_joints` joints.
    """
    from nmjax.data.layout import dataset_root, read_meta

    data = detector.cfg.data
    parents = read_meta(data.name, data.root).get("parents")
    if parents is None:
        return None
    if len(parents) != num_joints:
        raise ValueError(
            f"{dataset_root(data.name, data.root) / 'meta.json'}: `parents` names {len(parents)} "
            f"joints but the joint files hold {num_joints}; regenerate or re-prepare the dataset"
        )
    return np.asarray(parents)


def skeleton_against_truth(
    keypoints: list[np.ndarray],
    joints: list[np.ndarray],
    skeleton: tuple[np.ndarray, np.ndarray],
    true_parents: np.ndarray | None,
    names: list[str],
) -> dict[str, Any]:
    """The skeleton measures of `metrics.skeleton_agreement` over every test frame, named as
    results.json names them.

    The joint distance is the mean over test sequences of each sequence's mean over its joints
    and frames (sequences weigh alike, as in the tracking Chamfer), with the 95% CI over
    sequences; the other measures pool all the frames (a node's joint and a joint's node are the
    most frequent over the whole test split).

    Args:
      keypoints: per sequence, (C, T, K, 4) keypoints of its crops.
      joints: per sequence, (C, T, J, 3) ground-truth joints of the same crops.
      skeleton: (pruned parents (K,), kept nodes (K,) bool), `runs.pruned_skeleton`.
      true_parents: (J,) the true tree, or None (edge precision and bone recall left out).
      names: the sequence names.

    Returns:
      {"joint_distance": {"mean", "ci95", "n", "per_sequence"}, "joint_coverage_0.05",
       "joint_coverage_0.10", "edge_precision", "edge_precision_within_2_hops", "bone_recall"
       (the last three only with `true_parents`), "distinct_nodes", "skeleton_kept_nodes"}.
    """
    parents, kept = skeleton
    per_seq = {
        name: float(metrics.joint_distance(kp, gt, kept))
        for name, kp, gt in zip(names, keypoints, joints, strict=True)
    }
    flat_kp = np.concatenate([kp.reshape(-1, *kp.shape[-2:]) for kp in keypoints])
    flat_gt = np.concatenate([gt.reshape(-1, *gt.shape[-2:]) for gt in joints])
    scores = metrics.skeleton_agreement(flat_kp, flat_gt, kept, parents, true_parents)
    scores["joint_distance"] = {**summarize(list(per_seq.values())), "per_sequence": per_seq}
    scores["skeleton_kept_nodes"] = int(kept.sum())
    return scores


def evaluate_phase1(detector: Detector, max_crops: int = 8, split: str = "test") -> dict:
    """SC-score (Table 1), 4D-tracking Chamfer x1e4 (Table 2), bone-length variation and the
    skeleton against the ground truth on `split`.

    SC is reported in both definitions (`metrics.SC_NODES`): "sc" is the published one
    (per-frame candidates with alpha >= 0.2), "sc_fixed_nodes" the fixed node set of the pruned
    skeleton. The bone-length variation (`metrics.bone_length_variation`) and the skeleton
    measures (`skeleton_against_truth`) take the pruned tree and kept nodes stored in the run's
    skeleton.json (`runs.pruned_skeleton`): the bones between kept nodes over the same crops
    (each crop one sequence of T frames), absent when the run has no skeleton yet; the skeleton
    against the true tree of the dataset's meta.json (`true_tree`), absent without ground-truth
    joints or a skeleton.

    Returns:
      {"sc": {"score", "std_over_joints", "per_sequence"}, "sc_fixed_nodes": {same} (both absent
       without ground-truth joints), "tracking": {"mean", "ci95", "n", "per_sequence"},
       "bone_length_variation": {"mean", "kept_nodes", "per_sequence"}, and the keys of
       `skeleton_against_truth`}.
    """
    sc = metrics.SemanticConsistency()
    per_seq_sc: dict[str, dict[str, float]] = {"per_frame": {}, "fixed": {}}
    per_seq_cd, per_seq_bones, all_keypoints = {}, {}, []
    truth: dict[str, list] = {"names": [], "keypoints": [], "joints": []}
    skeleton = runs.pruned_skeleton(detector.run)
    for name, voxels, joints, keypoints, recon in phase1_outputs(detector, max_crops, split):
        per_seq_cd[name] = float(
            np.mean([metrics.tracking_chamfer(v, r) for v, r in zip(voxels, recon, strict=True)])
        )
        if joints is not None:
            sc.update(keypoints, joints)
            for nodes in metrics.SC_NODES:
                per_seq_sc[nodes][name] = metrics.semantic_consistency(
                    keypoints, joints, nodes=nodes
                )
            for key, value in (("names", name), ("keypoints", keypoints), ("joints", joints)):
                truth[key].append(value)
        if skeleton is not None:
            parents, kept = skeleton
            per_seq_bones[name] = float(
                metrics.bone_length_variation(keypoints, parents, kept=kept)
            )
            all_keypoints.append(keypoints)
    out: dict[str, Any] = {
        "tracking": {**summarize(list(per_seq_cd.values())), "per_sequence": per_seq_cd}
    }
    if sc.frames > 0:
        for key, nodes in (("sc", "per_frame"), ("sc_fixed_nodes", "fixed")):
            out[key] = {
                "score": sc.result(nodes),
                "std_over_joints": float(np.std(sc.per_joint(nodes))),
                "per_sequence": per_seq_sc[nodes],
            }
    if skeleton is not None and all_keypoints:
        parents, kept = skeleton
        out["bone_length_variation"] = {
            "mean": float(
                metrics.bone_length_variation(np.concatenate(all_keypoints), parents, kept=kept)
            ),
            "kept_nodes": int(kept.sum()),
            "per_sequence": per_seq_bones,
        }
    if skeleton is not None and truth["names"]:
        true_parents = true_tree(detector, truth["joints"][0].shape[-2])
        out.update(
            skeleton_against_truth(
                truth["keypoints"], truth["joints"], skeleton, true_parents, truth["names"]
            )
        )
    return out


def phase1_scores(results: dict) -> dict[str, float]:
    """The headline numbers of `evaluate_phase1`'s results, flat: "tracking_cd" and
    "tracking_cd_ci95"; "sc", "sc_fixed_nodes" and each one's "_std_over_joints" (with
    ground-truth joints); "bone_length_variation" (with a skeleton); "joint_distance" and
    "joint_distance_ci95" and the other skeleton measures (`SKELETON_TRUTH_COLUMNS`) with
    "skeleton_kept_nodes" (with joints and a skeleton)."""
    scores = {
        "tracking_cd": results["tracking"]["mean"],
        "tracking_cd_ci95": results["tracking"]["ci95"],
    }
    for key in ("sc", "sc_fixed_nodes"):
        if key in results:
            scores[key] = results[key]["score"]
            scores[f"{key}_std_over_joints"] = results[key]["std_over_joints"]
    if "bone_length_variation" in results:
        scores["bone_length_variation"] = results["bone_length_variation"]["mean"]
    if "joint_distance" in results:
        scores["joint_distance"] = results["joint_distance"]["mean"]
        scores["joint_distance_ci95"] = results["joint_distance"]["ci95"]
    for key in [k for k, _ in SKELETON_TRUTH_COLUMNS[1:]] + ["skeleton_kept_nodes"]:
        if key in results:
            scores[key] = results[key]
    return scores


def keyframe_starts(num_frames: int, rate: int, max_segments: int) -> np.ndarray:
    """Start keyframes ts = 0, SR, 2 SR, ... with ts + SR inside the sequence, at most M of them."""
    starts = np.arange(0, num_frames - rate, rate)
    if len(starts) > max_segments:
        starts = starts[np.linspace(0, len(starts) - 1, max_segments).astype(int)]
    return starts


def keyframe_clips(
    detector: Detector,
    seq,
    starts: np.ndarray,
    rate: int,
    sequence: tuple[np.ndarray, np.ndarray | None] | None,
    frames: int,
    voxels: bool,
) -> tuple[np.ndarray, np.ndarray | None]:
    """The clips x_ts .. x_te (te = ts + SR) of the interpolation evaluation.

    Args:
      detector: the phase-1 detector.
      seq: the test `Sequence`.
      starts: (n,) keyframes ts, in sampled frames.
      rate: SR.
      sequence: ("sequence" inputs) the sequence's keypoints (S, K, 4) from keypoints_<split>.npz
        and voxels (S, G, G, G) of one box over the whole sequence (None without `voxels`); the
        clips are cut from them. None ("crop" inputs): every clip is max(T, SR + 1) frames from
        ts normalised with its own bounding box and run through the detector as one crop, as the
        release's interpolation takes its keyframes.
      frames: T of phase 2 ("crop" inputs).
      voxels: also return the clips' voxels.

    Returns:
      keypoints (n, SR + 1, K, 4) and voxels (n, SR + 1, G, G, G) or None.
    """
    if sequence is not None:
        kp, vox = sequence
        index = starts[:, None] + np.arange(rate + 1)
        return kp[index], (vox[index] if voxels else None)
    data = detector.cfg.data
    length = max(frames, rate + 1)
    clips = [(seq, int(t) * data.sample_rate) for t in starts]
    kp = runs.detect_clips(detector, clips, length)[:, : rate + 1]
    if not voxels:
        return kp, None
    vox = np.stack([runs.clip_voxels(s, t, length, data)[: rate + 1] for s, t in clips])
    return kp, vox


def evaluate_interpolation(
    detector: Detector,
    interpolators: Interpolators,
    trajectories: dict[str, np.ndarray] | None,
    rates: tuple[int, ...] = SAMPLING_RATES,
    max_segments: int = 4,
    chunk: int = 4,
    seed: int = 0,
    split: str = "test",
    methods: tuple[str, ...] = METHODS,
    voxels: bool = True,
    keypoint_errors: dict | None = None,
    frames: int = 20,
) -> dict[str, dict[str, dict]]:
    """M-CD (Eq. 22) x1e3 of every method at every sampling rate, per test sequence.

    Alongside, when `keypoint_errors` is a dict it is filled in the same layout with the squared
    xyz error of the in-between keypoints against the observed ones (sum over K, mean over
    frames; a decoder-free check of the same interpolations).

    Args:
      detector: the phase-1 run's detector (its decoder turns keypoints into voxels).
      interpolators: the phase-2 models.
      trajectories: {sequence: (S, K, 4)} keypoints of `split` (keypoints_<split>.npz) for
        models trained on "sequence" inputs; None for "crop" inputs: each keyframe clip is then
        normalised on its own and run through the detector (`keyframe_clips`).
      rates: sampling rates SR (gap between keyframes, in sampled frames).
      max_segments: keyframe pairs per sequence and rate, spread over the sequence.
      chunk: keyframe pairs decoded at once (fixed, so each rate compiles once).
      seed: PRNG seed of the generative methods.
      split: the split whose sequences are evaluated.
      methods: the methods to run (VRNN is dropped when no VRNN model is given).
      voxels: decode and score M-CD; False computes only `keypoint_errors` (much faster).
      keypoint_errors: optional dict to receive the keypoint errors.
      frames: T of phase 2, the shortest clip detected on "crop" inputs.

    Returns:
      {method: {str(SR): {"mean", "ci95", "n", "per_sequence"}}}; methods without a model left
      out.
    """
    from nmjax.data.datasets import load_sequences

    cfg = detector.cfg
    methods = [m for m in methods if m != "VRNN" or interpolators.vrnn is not None]
    per_seq: dict[str, dict[int, dict[str, float]]] = {m: {r: {} for r in rates} for m in methods}
    kp_seq: dict[str, dict[int, dict[str, float]]] = {m: {r: {} for r in rates} for m in methods}
    key = jax.random.key(seed)
    for seq in load_sequences(cfg.data.name, split, cfg.data.root):
        sequence = None
        if trajectories is not None:
            if seq.name not in trajectories:
                raise ValueError(
                    f"sequence {seq.name!r} of the {split} split has no keypoints in the phase-1 "
                    f"run's keypoints_{split}.npz; re-export them with "
                    f"`nmjax export-keypoints --run {detector.run}`"
                )
            vox = runs.sequence_voxels(seq, cfg.data.sample_rate, cfg.data.grid) if voxels else None
            sequence = (trajectories[seq.name], vox)
        sampled = -(-seq.num_frames // cfg.data.sample_rate)  # frames of the sampled sequence
        for rate in rates:
            starts = keyframe_starts(sampled, rate, max_segments)
            if len(starts) == 0:
                continue  # the sequence is shorter than one gap
            scores: dict[str, list[float]] = {m: [] for m in methods}
            kp_err: dict[str, list[float]] = {m: [] for m in methods}
            for i in range(0, len(starts), chunk):
                ts = starts[i : i + chunk]
                ts = pad_with_last(ts, chunk)  # a fixed shape: one compilation per rate
                real = min(chunk, len(starts) - i)
                kp, vox = keyframe_clips(detector, seq, ts, rate, sequence, frames, voxels)
                key, sub = jax.random.split(key)
                for method in methods:
                    x = interpolators.run(method, kp[:, 0], kp[:, -1], rate, sub)
                    inner = np.sum((x[:real, 1:-1, :, :3] - kp[:real, 1:-1, :, :3]) ** 2, -1)
                    kp_err[method] += list(np.mean(np.sum(inner, -1), -1)) if rate > 1 else []
                    if not voxels:
                        continue
                    recon = detector.decode(x, vox[:, 0])
                    for j in range(real):
                        mcd = metrics.motion_chamfer(vox[j], recon[j])
                        scores[method].append(mcd * MCD_SCALE)
            for method in methods:
                if voxels:
                    per_seq[method][rate][seq.name] = float(np.mean(scores[method]))
                if kp_err[method]:
                    kp_seq[method][rate][seq.name] = float(np.mean(kp_err[method]))
    if keypoint_errors is not None:
        keypoint_errors.update(summarize_per_rate(kp_seq))
    return summarize_per_rate(per_seq)


def summarize_per_rate(per_sequence: dict[str, dict[int, dict[str, float]]]) -> dict:
    """The summary over sequences (`summarize`) of every method at every sampling rate.

    Args:
      per_sequence: {method: {SR: {sequence: score}}}.

    Returns:
      {method: {str(SR): {"mean", "ci95", "n", "per_sequence"}}}.
    """
    return {
        method: {
            str(rate): {**summarize(list(scores.values())), "per_sequence": scores}
            for rate, scores in by_rate.items()
        }
        for method, by_rate in per_sequence.items()
    }


# --- generation: diversity, bone-length error, set distance to real motion --------------------

GEN_HORIZONS = (25, 100, 300)
GEN_METHODS = ("Ours", "VRNN", "Hold last pose")
REFERENCE = "Test clips (reference)"
# measure -> (section title, what its confidence interval is over)
GEN_MEASURES = {
    "diversity": (
        "Diversity: APD of the S samples of one conditioning clip",
        "95% CI over conditioning clips",
    ),
    "set_diversity": (
        "Diversity of the generated set as a whole (mean distance to every other generated clip)",
        "95% CI over conditioning clips; reference: the real test clips of the same length",
    ),
    "bone_error": (
        "Bone-length error of the generated frames (`bone_length_variation`, pruned skeleton)",
        "95% CI over conditioning clips; reference: the real test clips of the same length",
    ),
    "set_distance": (
        "Set distance to real test clips (bidirectional Chamfer, root translation removed)",
        "CI of the two terms below combined in quadrature",
    ),
    "to_real": (
        "Set distance, first term: generated clip -> nearest real clip (do samples look real?)",
        "95% CI over conditioning clips",
    ),
    "to_generated": (
        "Set distance, second term: real clip -> nearest generated clip (is the data covered?)",
        "95% CI over real clips",
    ),
}
GENERATION_METRICS = {name: title for name, (title, _) in GEN_MEASURES.items()}


def conditioning_clips(
    trajectories: dict[str, np.ndarray], cond: int, per_sequence: int
) -> tuple[list[tuple[str, int]], np.ndarray]:
    """Conditioning clips of `cond` frames, `per_sequence` starts spread over every sequence.

    Returns:
      [(sequence, start frame)] and x_cond (B, cond, K, 4).
    """
    clips, frames = [], []
    for name in sorted(trajectories):
        x = trajectories[name]
        if len(x) < cond:
            continue
        starts = np.unique(np.linspace(0, len(x) - cond, per_sequence).astype(int))
        clips += [(name, int(t)) for t in starts]
        frames += [x[t : t + cond] for t in starts]
    if not frames:
        longest = max(len(x) for x in trajectories.values())
        raise ValueError(
            f"no test sequence has {cond} frames to condition on (longest: {longest}); lower --cond"
        )
    return clips, np.stack(frames).astype(np.float32)


def real_clips(
    trajectories: dict[str, np.ndarray], frames: int, stride: int, per_sequence: int
) -> np.ndarray:
    """Real clips of `frames` frames: windows starting every `stride` frames of every sequence
    that is at least that long, at most `per_sequence` (spread) per sequence.

    Returns:
      (M, frames, K, 4); M = 0 when no sequence has `frames` frames.
    """
    windows = []
    for name in sorted(trajectories):
        x = trajectories[name]
        starts = np.arange(0, len(x) - frames + 1, stride)
        if len(starts) > per_sequence:
            starts = starts[np.linspace(0, len(starts) - 1, per_sequence).astype(int)]
        windows += [x[t : t + frames] for t in starts]
    k = next(iter(trajectories.values())).shape[1]
    return np.stack(windows) if windows else np.zeros((0, frames, k, 4), np.float32)


def hold_last_pose(x_cond: np.ndarray, frames: int, samples: int) -> np.ndarray:
    """The hold-last-pose baseline: the last conditioning frame repeated, (B, S, frames, K, 4).

    Its S samples are identical (diversity 0) and nothing moves (bone-length error 0).
    """
    b, _, k, c = x_cond.shape
    return np.broadcast_to(x_cond[:, None, -1:], (b, samples, frames, k, c))


def generated_futures(
    model: tuple[Any, Any], x_cond: np.ndarray, frames: int, samples: int, key: jax.Array
) -> np.ndarray:
    """The `frames` generated frames after x_cond (B, T_cond, K, 4): (B, S, frames, K, 4)."""
    keypoints, _ = tasks.generate_jit(
        *model, jnp.asarray(x_cond), key, num_frames=frames, num_samples=samples
    )
    return np.asarray(keypoints)[:, :, x_cond.shape[1] :]


@jax.jit
def _bone_error(clips, parents, kept):  # (B, S, N, K, 4) -> (B,), one value per conditioning clip
    """`bone_length_variation` on the bones of the run's pruned skeleton (`kept` nodes), whatever
    intensities the model generates."""
    return jax.vmap(lambda x: metrics.bone_length_variation(x, parents, kept=kept))(clips)


_diversity = jax.jit(metrics.diversity)
_set_diversity = jax.jit(metrics.set_diversity)
_nearest_clips = jax.jit(metrics.nearest_clip_distances, static_argnames="root")


def _floats(values) -> list[float]:
    return [float(v) for v in np.asarray(values).ravel()]


def generation_measures(
    futures: np.ndarray,
    real: np.ndarray,
    parents: np.ndarray,
    kept: np.ndarray,
    root: int,
    no_real: str = "no real clip",
) -> dict[str, dict]:
    """The measures of one method at one horizon.

    Args:
      futures: (B, S, N, K, 4) generated frames, S samples for each of B conditioning clips.
      real: (M, N, K, 4) real test clips of the same length (M may be 0).
      parents: (K,) the pruned skeleton (`pruned_skeleton`); kept: (K,) its nodes, the
        keypoints every distance averages over.
      root: the skeleton's root keypoint (its trajectory is removed for the set distance).
      no_real: the reason recorded when `real` is empty.

    Returns:
      {"diversity" (absent for S = 1), "set_diversity", "bone_error": summaries over the B
      clips; "set_distance": {"mean", "ci95", "n", "to_real", "to_generated"} or, with no real
      clip, {"mean": nan, "ci95": nan, "n": 0, "reason"}}.
    """
    b, s = futures.shape[:2]
    mask = jnp.asarray(kept)
    out: dict[str, dict] = {}
    if s >= 2:
        out["diversity"] = summarize(_floats(_diversity(jnp.asarray(futures), mask)))
    out["set_diversity"] = summarize(_floats(_set_diversity(jnp.asarray(futures), mask)))
    bones = _bone_error(jnp.asarray(futures), jnp.asarray(parents), jnp.asarray(kept))
    out["bone_error"] = summarize(_floats(bones))
    if len(real) == 0:
        out["set_distance"] = {
            "mean": float("nan"),
            "ci95": float("nan"),
            "n": 0,
            "reason": no_real,
        }
        return out
    flat = jnp.asarray(futures.reshape(b * s, *futures.shape[2:]))
    to_real, to_generated = _nearest_clips(flat, jnp.asarray(real), root=root, mask=mask)
    per_clip = np.asarray(to_real).reshape(b, s).mean(axis=1)  # its mean is the Chamfer term
    tr, tg = summarize(_floats(per_clip)), summarize(_floats(to_generated))
    out["set_distance"] = {
        "mean": tr["mean"] + tg["mean"],
        # The two terms are means over different clips; their CIs are combined as if
        # independent.
        "ci95": math.hypot(tr["ci95"], tg["ci95"]),
        "n": tr["n"],
        "to_real": tr,
        "to_generated": tg,
    }
    return out


def real_reference(real: np.ndarray, parents: np.ndarray, kept: np.ndarray) -> dict:
    """Bone-length error and set diversity of the real clips (M, N, K, 4), for comparison."""
    if len(real) < 2:
        return {"clips": int(len(real))}
    clips = real[:, None]  # every real clip its own group of one sample
    mask = jnp.asarray(kept)
    return {
        "clips": int(len(real)),
        "set_diversity": summarize(_floats(_set_diversity(jnp.asarray(clips), mask))),
        "bone_error": summarize(
            _floats(_bone_error(jnp.asarray(clips), jnp.asarray(parents), jnp.asarray(kept)))
        ),
    }


def evaluate_generation(
    models: dict[str, tuple[Any, Any]],
    trajectories: dict[str, np.ndarray],
    parents: np.ndarray,
    kept: np.ndarray,
    *,
    horizons: tuple[int, ...] = GEN_HORIZONS,
    cond: int = 5,
    samples: int = 10,
    clips: int = 4,
    stride: int = 5,
    real_per_sequence: int = 16,
    seed: int = 0,
    real_trajectories: dict[str, np.ndarray] | None = None,
    conditioning: tuple[list[tuple[str, int]], np.ndarray] | None = None,
) -> dict:
    """Diversity, bone-length error and set distance to real motion of generated motion at
    several horizons, for each model and the hold-last-pose baseline.

    Every method continues the same conditioning clips (`clips` per test sequence, `cond`
    frames each); the models draw `samples` futures of max(horizons) frames per clip once, and
    horizon N measures their first N generated frames (the `cond` posterior frames excluded).
    Real clips of N frames are cut from the test sequences of at least N frames
    (`real_clips`); at a horizon no test sequence reaches the set distance is n/a, with the
    reason. All distances average over the kept nodes of the pruned skeleton.

    Args:
      models: {method: (graphdef, state)} of phase-2 models, e.g. {"Ours": ..., "VRNN": ...}.
      trajectories: {sequence: (T_seq, K, 4)} test keypoints (keypoints_test.npz).
      parents, kept: the pruned skeleton and its node mask (`pruned_skeleton`).
      horizons: generated frames N measured (each >= 2).
      cond: T_cond observed frames.
      samples: S futures per conditioning clip.
      clips: conditioning clips per test sequence.
      stride, real_per_sequence: spacing and number per sequence of the real clips.
      seed: PRNG seed of the samples.
      real_trajectories: {sequence: (T_seq, K, 4)} the real clips are cut from instead of the
        test keypoints, e.g. the detector's keypoints of longer sequences of the same body
        (`runs.export_keypoints(..., data_root=...)`), so that long horizons have real clips.
      conditioning: ([(sequence, start)], x_cond (B, cond, K, 4)) the clips to condition on;
        default `conditioning_clips` of `trajectories` (the models' "crop" inputs pass the same
        clips detected on their own, `crop_conditioning`).

    Returns:
      {"clips": [[sequence, start]], "methods": {method: {str(N): `generation_measures`}},
       "real": {str(N): `real_reference`}}.
    """
    if not horizons or min(horizons) < 2:
        raise ValueError(f"generation horizons must be >= 2 frames, got {horizons}")
    parents, kept = np.asarray(parents), np.asarray(kept, bool)
    root = int(np.flatnonzero(parents == np.arange(len(parents)))[0])
    names, x_cond = conditioning_clips(trajectories, cond, clips)
    if conditioning is not None:
        names, x_cond = conditioning
    longest = max(horizons)
    futures = {
        method: generated_futures(model, x_cond, longest, samples, jax.random.key(seed))
        for method, model in models.items()
    }
    futures["Hold last pose"] = hold_last_pose(x_cond, longest, samples)
    out: dict[str, Any] = {"clips": [list(c) for c in names], "methods": {}, "real": {}}
    reference = trajectories if real_trajectories is None else real_trajectories
    most = max(len(x) for x in reference.values())
    for n in horizons:
        real = real_clips(reference, n, stride, real_per_sequence)
        out["real"][str(n)] = real_reference(real, parents, kept)
        source = "test" if real_trajectories is None else "real"
        no_real = f"no {source} sequence has {n} frames; the longest has {most}"
        for method, x in futures.items():
            measures = generation_measures(x[:, :, :n], real, parents, kept, root, no_real)
            out["methods"].setdefault(method, {})[str(n)] = measures
    return out


def _generation_entry(measures: dict, measure: str) -> dict | str:
    """The summary of `measure` in one method's measures at one horizon, or why there is none."""
    distance = measures["set_distance"]
    if measure in ("to_real", "to_generated"):
        return distance.get(measure) or distance["reason"]
    if measure == "set_distance" and "reason" in distance:
        return distance["reason"]
    return measures.get(measure) or "one sample per clip"


def generation_tables(gen: dict) -> list[str]:
    """Markdown lines of the generation evaluation: one table per measure, methods x horizons."""
    methods = gen["methods"]
    horizons = list(next(iter(methods.values())).keys())
    lines: list[str] = []
    for measure, (title, ci) in GEN_MEASURES.items():
        lines += [
            f"### {title}",
            "",
            f"Mean ({ci}).",
            "",
            "| method | " + " | ".join(f"N = {n}" for n in horizons) + " |",
            "|---|" + "---|" * len(horizons),
        ]
        rows = {
            m: [_generation_entry(by_n[n], measure) for n in horizons]
            for m, by_n in methods.items()
        }
        if measure in ("set_diversity", "bone_error"):
            rows[REFERENCE] = [
                gen["real"][n].get(measure) or f"{gen['real'][n]['clips']} test clips of {n} frames"
                for n in horizons
            ]
        for method, entries in rows.items():
            cells = [
                fmt(e["mean"], e["ci95"]) if isinstance(e, dict) else f"n/a ({e})" for e in entries
            ]
            lines.append(f"| {method} | " + " | ".join(cells) + " |")
        lines.append("")
    return lines


# --- tables and plots ---------------------------------------------------------------------------


def fmt(value: float, ci: float | None = None) -> str:
    """'1.23 (0.045)' with three significant digits; 'n/a' for NaN."""
    if value is None or not np.isfinite(value):
        return "n/a"
    text = f"{value:.3g}"
    return text if ci is None else f"{text} ({ci:.3g})" if np.isfinite(ci) else f"{text} (n/a)"


# The skeleton measures in every phase-1 table: (results key, column title).
SKELETON_TRUTH_COLUMNS = (
    ("joint_distance", "joint distance (95% CI)"),
    ("joint_coverage_0.05", "coverage r = 0.05"),
    ("joint_coverage_0.10", "coverage r = 0.10"),
    ("edge_precision", "edge precision"),
    (
        f"edge_precision_within_{metrics.TWO_HOPS}_hops",
        f"edge precision, within {metrics.TWO_HOPS} hops",
    ),
    ("bone_recall", "bone recall"),
    ("distinct_nodes", "distinct / kept nodes"),
)
SKELETON_TRUTH_NOTE = (
    "On the nodes the run's skeleton.json keeps, over the test split (n/a: the data lacks "
    "joints or its meta.json lacks the true tree): joint distance = mean distance from a joint "
    "to its nearest kept node (cube [-1, 1]^3; 95% CI over sequences); coverage = share of "
    "joint-frames with a kept node within r; edge precision = share of skeleton edges whose "
    "nodes' joints are the same or adjacent in the true tree (or within "
    f"{metrics.TWO_HOPS} hops); bone recall = share of true bones whose joints' nodes are the "
    "same or adjacent in the skeleton; distinct = kept nodes that are some joint's node."
)


def skeleton_truth_table(rows: dict[str, dict], sc: bool = False) -> list[str]:
    """Markdown lines of one table of the skeleton measures (`SKELETON_TRUTH_COLUMNS`), one row
    per {label: phase-1 results of `evaluate_phase1`}; `sc` puts both SC-scores in front.
    "n/a" where a row lacks a measure; no lines when no row has any."""
    if not any("joint_distance" in p1 for p1 in rows.values()):
        return []
    titles = (["SC", "SC fixed nodes"] if sc else []) + [t for _, t in SKELETON_TRUTH_COLUMNS]
    lines = ["| model | " + " | ".join(titles) + " |", "|---|" + "---|" * len(titles)]
    for label, p1 in rows.items():
        cells = [fmt(p1[k]["score"]) if k in p1 else "n/a" for k in ("sc", "sc_fixed_nodes")]
        cells = cells if sc else []
        for key, _ in SKELETON_TRUTH_COLUMNS:
            value = p1.get(key)
            if value is None:
                cells.append("n/a")
            elif key == "joint_distance":
                cells.append(fmt(value["mean"], value["ci95"]))
            elif key == "distinct_nodes":
                cells.append(f"{value} / {p1['skeleton_kept_nodes']}")
            else:
                cells.append(fmt(value))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def markdown_tables(results: dict) -> str:
    """The evaluation as markdown: Table 1, Table 2 and Tables 11-12 layouts."""
    lines = [f"# Evaluation of {results['run']}", ""]
    p1 = results.get("phase1", {})
    if "sc" in p1:
        sc, fixed = p1["sc"], p1.get("sc_fixed_nodes")
        lines += [
            "## SC-score (Eq. 21, paper Table 1)",
            "",
            "| model | SC-score, published: per-frame alpha >= 0.2 (std over joints) "
            "| SC-score, fixed node set (std) |",
            "|---|---|---|",
            f"| Ours | {fmt(sc['score'], None)} ({sc['std_over_joints']:.3g}) | "
            + (f"{fmt(fixed['score'], None)} ({fixed['std_over_joints']:.3g})" if fixed else "n/a")
            + " |",
            "",
        ]
    if "bone_length_variation" in p1:
        bones = p1["bone_length_variation"]
        lines += [
            "## Bone-length variation (std / mean of each bone's length over time)",
            "",
            "| model | variation | kept nodes |",
            "|---|---|---|",
            f"| Ours | {fmt(bones['mean'])} | {bones['kept_nodes']} |",
            "",
        ]
    table = skeleton_truth_table({"Ours": p1})
    if table:
        lines += ["## Skeleton against the ground truth", "", SKELETON_TRUTH_NOTE, "", *table, ""]
    if "tracking" in p1:
        tr = p1["tracking"]
        lines += [
            "## 4D-tracking Chamfer distance x1e4 (paper Table 2)",
            "",
            "| model | CD x1e4 (95% CI over sequences) | sequences |",
            "|---|---|---|",
            f"| Ours | {fmt(tr['mean'], tr['ci95'])} | {tr['n']} |",
            "",
        ]
    for key, title in (
        ("interpolation", "Interpolation M-CD x1e3 (Eq. 22, paper Tables 11-12; 95% CI)"),
        (
            "interpolation_keypoints",
            "In-between keypoint error, sum over K of squared xyz (95% CI)",
        ),
    ):
        lines += interpolation_table(results.get(key), title)
    return "\n".join(lines)


def interpolation_table(mcd: dict | None, title: str) -> list[str]:
    """Markdown lines of one {method: {SR: summary}} table (Tables 11-12 layout)."""
    lines: list[str] = []
    if mcd:
        rates = list(next(iter(mcd.values())).keys())
        lines += [
            f"## {title}",
            "",
            "| model | " + " | ".join(f"SR = {r}" for r in rates) + " | Average |",
            "|---|" + "---|" * (len(rates) + 1),
        ]
        for method, by_rate in mcd.items():
            means = [by_rate[r]["mean"] for r in rates]
            cells = [fmt(by_rate[r]["mean"], by_rate[r]["ci95"]) for r in rates]
            finite = [m for m in means if np.isfinite(m)]
            avg = float(np.mean(finite)) if finite else float("nan")
            lines.append(f"| {method} | " + " | ".join(cells) + f" | {fmt(avg)} |")
        lines.append("")
    return lines


# --- the command ---------------------------------------------------------------------------------


def crop_conditioning(
    detector: Detector, clips: list[tuple[str, int]], cond: int, frames: int
) -> np.ndarray:
    """x_cond (B, cond, K, 4) of conditioning clips as the release's generation takes it.

    Each clip (sequence, start in sampled frames) is its first crop, max(T, cond) frames,
    normalised with its own bounding box; its first `cond` frames go through the detector on
    their own (`runs.detect_clips`).
    """
    seqs, rate = runs.split_sequences(detector, "test"), detector.cfg.data.sample_rate
    located = [(seqs[name], start * rate) for name, start in clips]
    return runs.detect_clips(detector, located, max(frames, cond), detect=cond)


def evaluate_generation_run(
    run: str | Path,
    *,
    vrnn_run: str | Path | None = None,
    out: str | Path | None = None,
    horizons: tuple[int, ...] = GEN_HORIZONS,
    cond: int = 5,
    samples: int = 10,
    clips: int = 4,
    seed: int = 0,
    real_keypoints: str | Path | None = None,
) -> dict:
    """The generation evaluation (`evaluate_generation`) of an "nm" run, its VRNN baseline (given
    or found beside it) and hold-last-pose; writes generation.json, generation.md and
    generation.png into `out` (default RUN/eval). `real_keypoints`: an .npz of keypoint
    sequences (the layout of keypoints_test.npz) to cut the real clips from."""
    run = Path(run)
    stamp = provenance.stamp(GENERATION_METRICS)
    if runs.run_kind(run) != "dyn":
        raise ValueError(
            f"{run} is a phase-1 run; --generation needs a phase-2 'nm' run (nmjax train-dyn)"
        )
    dyn_cfg, skel_run, vrnn_run = runs.phase2_runs(run, vrnn_run)
    skeleton = runs.pruned_skeleton(skel_run)
    if skeleton is None:
        raise FileNotFoundError(
            f"{skel_run}/skeleton.json not found; run `nmjax extract-skeleton --run {skel_run}`"
        )
    trajectories = runs.load_trajectories(skel_run, "test")
    conditioning = None
    if dyn_cfg.inputs == "crop":
        names, _ = conditioning_clips(trajectories, cond, clips)
        x_cond = crop_conditioning(runs.phase2_detector(skel_run), names, cond, dyn_cfg.frames)
        conditioning = (names, x_cond)
    models = {"Ours": nnx.split(runs.restore_dynamics(run))}
    if vrnn_run is not None:
        models["VRNN"] = nnx.split(runs.restore_dynamics(vrnn_run))
    settings = {"horizons": list(horizons), "cond": cond, "samples": samples, "clips": clips}
    settings["inputs"] = dyn_cfg.inputs
    real = None
    if real_keypoints is not None:
        real = runs.read_trajectories(Path(real_keypoints))
        settings["real_keypoints"] = str(real_keypoints)
    gen = evaluate_generation(
        models,
        trajectories,
        *skeleton,
        horizons=horizons,
        cond=cond,
        samples=samples,
        clips=clips,
        seed=seed,
        real_trajectories=real,
        conditioning=conditioning,
    )
    results = {
        "provenance": stamp,
        "run": str(run),
        "skel_run": str(skel_run),
        "vrnn_run": None if vrnn_run is None else str(vrnn_run),
        "settings": {**settings, "seed": seed, "kept_nodes": int(skeleton[1].sum())},
        **gen,
    }
    out = Path(out) if out is not None else run / "eval"
    atomic.write_json(out / "generation.json", results)
    provenance.write_markdown(out / "generation.md", generation_markdown(results), stamp)
    from nmjax import viz  # matplotlib only where a picture is drawn

    viz.plot_generation(
        out / "generation.png", results, reference=REFERENCE, title=f"{run.name}: generation"
    )
    provenance.stamp_png(out / "generation.png", stamp)
    return results


INPUTS_NOTE = {
    "crop": "each clip's first crop normalised on its own, its first frames detected alone",
    "sequence": "the whole-sequence export",
}


def generation_markdown(results: dict) -> str:
    """generation.md: what was measured, then the tables of `generation_tables`."""
    st = results["settings"]
    n_clips = len(results["clips"])
    head = [
        f"# Generation of {results['run']}",
        "",
        f"VRNN baseline: {results['vrnn_run'] or 'none found'}. {n_clips} conditioning clips of "
        f"{st['cond']} test frames ({st['clips']} per test sequence; keypoints of "
        f"{INPUTS_NOTE.get(st.get('inputs', 'sequence'), st.get('inputs'))}), {st['samples']} "
        f"samples each; horizon N = frames generated after them; the real clips are cut from "
        f"{st.get('real_keypoints', 'keypoints_test.npz')} (whole sequences). Distances are mean "
        f"per-frame keypoint distances (Euclidean, xyz, normalised units) over the "
        f"{st['kept_nodes']} nodes of the pruned skeleton. Hold last pose repeats the last "
        "conditioning frame: diversity and bone-length error 0 by construction (up to float "
        "round-off). Ours keeps every bone of "
        "its full tree exactly (forward kinematics with the lengths of the conditioning "
        "frames); a bone of the pruned tree that skips a pruned joint can still change length.",
        "",
    ]
    return "\n".join(head + generation_tables(results))


def evaluate_run(
    run: str | Path,
    *,
    vrnn_run: str | Path | None = None,
    out: str | Path | None = None,
    rates: tuple[int, ...] = SAMPLING_RATES,
    trajectories: int = 16,
    max_segments: int = 4,
    max_crops: int = 8,
    seed: int = 0,
) -> dict:
    """Evaluates a phase-2 run (all tables) or a phase-1 run (Tables 1-2); writes the results."""
    run = Path(run)
    dyn = runs.run_kind(run) == "dyn"
    definitions = {**PHASE1_METRICS, **(INTERPOLATION_METRICS if dyn else {})}
    results: dict[str, Any] = {"provenance": provenance.stamp(definitions), "run": str(run)}
    if dyn:
        dyn_cfg, skel_run, vrnn_run = runs.phase2_runs(run, vrnn_run)
        results["skel_run"] = str(skel_run)
        results["vrnn_run"] = None if vrnn_run is None else str(vrnn_run)
    else:
        skel_run, dyn_cfg = run, None
    detector = Detector.load(skel_run)
    results["phase1"] = evaluate_phase1(detector, max_crops=max_crops)
    if dyn_cfg is not None:
        nm = nnx.split(runs.restore_dynamics(run))
        vrnn = None if vrnn_run is None else nnx.split(runs.restore_dynamics(vrnn_run))
        traj = None
        if dyn_cfg.inputs == "sequence":
            traj = runs.load_trajectories(skel_run, "test")
        interp = Interpolators(nm, vrnn, trajectories)
        kp_errors: dict = {}
        results["interpolation"] = evaluate_interpolation(
            detector,
            interp,
            traj,
            rates,
            max_segments=max_segments,
            seed=seed,
            keypoint_errors=kp_errors,
            frames=dyn_cfg.frames,
        )
        results["interpolation_keypoints"] = kp_errors
        results["settings"] = {
            "trajectories": trajectories,
            "max_segments": max_segments,
            "max_crops": max_crops,
            "seed": seed,
            "mcd_scale": MCD_SCALE,
            "inputs": dyn_cfg.inputs,
        }
    out = Path(out) if out is not None else run / "eval"
    atomic.write_json(out / "results.json", results)
    provenance.write_markdown(out / "tables.md", markdown_tables(results), results["provenance"])
    if "interpolation" in results:
        from nmjax import viz  # matplotlib only where a picture is drawn

        viz.plot_mcd(out / "mcd.png", results["interpolation"], title=str(run.name))
        provenance.stamp_png(out / "mcd.png", results["provenance"])
    return results
