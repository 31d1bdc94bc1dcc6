"""`nmjax evaluate --run RUN`: the paper's quantitative tables on the test split.

    nmjax evaluate --run runs/dyn-synth-hand-nm-... [--vrnn-run runs/dyn-...-vrnn-...] [--out DIR]
    nmjax evaluate --run runs/skel-synth-hand-...      (phase-1 metrics only)

- SC-score (Eq. 21, Table 1) and its standard deviation over ground-truth joints, on test crops
  of T frames (each crop normalised on its own, as in training), in the published definition
  ("sc": in each frame keypoints with alpha < 0.2 are no candidates) and with the fixed node set
  of the pruned skeleton ("sc_fixed_nodes").
- Bone-length variation of the pruned skeleton over the same crops (std / mean length per bone).
- 4D-tracking Chamfer x1e4 (Table 2): reconstruction of every crop thresholded at 0.5 against its
  voxels, averaged per sequence; mean and 95% confidence interval over test sequences.
- Interpolation M-CD (Eq. 22, Tables 11-12) at sampling rates SR = 3, 5, ..., 30 for Ours (the
  "nm" dynamics), VRNN (a positional "vrnn" run on the same phase-1 run, when one is given or
  found next to RUN), Lerp and Slerp. Keyframes x_ts, x_te = x_{ts+SR} are taken every SR frames
  of each test sequence (whole sequence normalised with one bounding box, as the phase-1 run's
  keypoints_test.npz); each method's keypoints are turned into voxels by the phase-1 decoder
  (gaussian maps of the keypoints + the features of frame ts, Eq. 7) thresholded at 0.5 and
  compared with the true voxels on difference voxels. Reported x1e3 (the paper does not state
  its scale); mean and 95% confidence interval over test sequences.

Writes `<out>/results.json`, `<out>/tables.md` and `<out>/mcd.png` (default out: `<run>/eval`).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import sys
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from nmjax import io, metrics, tasks
from nmjax.config import DynTrainConfig, SkelTrainConfig
from nmjax.train import common

SAMPLING_RATES = (3, 5, 10, 15, 20, 25, 30)
METHODS = ("Ours", "VRNN", "Lerp", "Slerp")
MCD_SCALE = 1e3


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


def run_kind(run: str | Path) -> str:
    """ "dyn" for a phase-2 run folder (its config names a `skel_run`), "skel" for phase 1."""
    path = Path(run) / common.CONFIG_FILE
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} not found; --run must be a run folder of `nmjax train-skel` or "
            "`nmjax train-dyn`"
        )
    try:
        config = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path} is not valid JSON ({err}); the run folder is damaged") from err
    return "dyn" if "skel_run" in config else "skel"


def find_vrnn_run(dyn_run: Path, skel_run: Path) -> Path | None:
    """A positional-baseline phase-2 run beside `dyn_run` trained on the same phase-1 run."""
    for candidate in sorted(Path(dyn_run).parent.glob("*"), reverse=True):
        if candidate == Path(dyn_run) or not (candidate / common.CONFIG_FILE).is_file():
            continue
        try:
            cfg = common.load_config(candidate, DynTrainConfig)
        except (ValueError, FileNotFoundError, TypeError):
            continue
        same = cfg.skel_run and Path(cfg.skel_run).resolve() == Path(skel_run).resolve()
        if cfg.model.model == "vrnn" and same and (candidate / "checkpoints").is_dir():
            return candidate
    return None


@dataclasses.dataclass
class Detector:
    """A restored phase-1 detector with compiled detect / reconstruct / decode functions."""

    run: Path
    cfg: SkelTrainConfig
    graphdef: Any
    state: Any

    @classmethod
    def load(cls, run: str | Path) -> Detector:
        from nmjax.train.skel import load_detector

        model, cfg = load_detector(run)
        graphdef, state = nnx.split(model)
        return cls(Path(run), cfg, graphdef, state)

    def run_batches(self, voxels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Keypoints (C, T, K, 4) and reconstructions (C, T, G, G, G) of crops (C, T, G, G, G).

        Crops go through in batches of the training batch size (the last one padded), so one
        compiled shape serves every call.
        """
        b = self.cfg.data.batch_size
        n = len(voxels)
        padded = np.concatenate([voxels, np.repeat(voxels[-1:], (-n) % b, axis=0)])
        kps, recons = [], []
        for i in range(0, len(padded), b):
            kp, recon = _forward(self.graphdef, self.state, jnp.asarray(padded[i : i + b]))
            kps.append(np.asarray(kp))
            recons.append(np.asarray(recon))
        return np.concatenate(kps)[:n], np.concatenate(recons)[:n]

    def decode(self, keypoints: np.ndarray, first_voxels: np.ndarray) -> np.ndarray:
        """Eq. 7 for given keypoints: (B, F, K, 4), first frame (B, G, G, G) -> (B, F, G, G, G)."""
        return np.asarray(
            _decode(self.graphdef, self.state, jnp.asarray(keypoints), jnp.asarray(first_voxels))
        )


@functools.partial(jax.jit, static_argnames="graphdef")
def _forward(graphdef, state, voxels):
    out = nnx.merge(graphdef, state)(voxels)
    return out["keypoints"], out["recon"]


@functools.partial(jax.jit, static_argnames="graphdef")
def _decode(graphdef, state, keypoints, first_voxels):
    model = nnx.merge(graphdef, state)
    features = model.features(first_voxels)  # c_1 of frame ts: f_feat sees one frame
    return model.decode(keypoints, features, first_voxels)


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


def evaluate_phase1(detector: Detector, max_crops: int = 8, split: str = "test") -> dict:
    """SC-score (Table 1), 4D-tracking Chamfer x1e4 (Table 2) and bone-length variation on
    `split`.

    SC is reported in both definitions (`metrics.SC_NODES`): "sc" is the published one
    (per-frame candidates with alpha >= 0.2), "sc_fixed_nodes" the fixed node set of the pruned
    skeleton. The bone-length variation (`metrics.bone_length_variation`) is measured on the
    pruned tree of the run's `skeleton.json` over the same crops (each crop one sequence of T
    frames); it is absent when the run has no skeleton yet.

    Returns:
      {"sc": {"score", "std_over_joints", "per_sequence"}, "sc_fixed_nodes": {same} (both absent
       without ground-truth joints), "tracking": {"mean", "ci95", "n", "per_sequence"},
       "bone_length_variation": {"mean", "kept_nodes", "per_sequence"}}.
    """
    sc = metrics.SemanticConsistency()
    per_seq_sc: dict[str, dict[str, float]] = {"per_frame": {}, "fixed": {}}
    per_seq_cd, per_seq_bones, all_keypoints = {}, {}, []
    skeleton = pruned_skeleton(detector.run)
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
        if skeleton is not None:
            per_seq_bones[name] = float(metrics.bone_length_variation(keypoints, skeleton[0]))
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
            "mean": float(metrics.bone_length_variation(np.concatenate(all_keypoints), parents)),
            "kept_nodes": int(kept.sum()),
            "per_sequence": per_seq_bones,
        }
    return out


def pruned_skeleton(run: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(parents of the pruned tree, kept-node mask) of a phase-1 run's `skeleton.json`, or None
    when the run has none (`skeleton.prune` with the intensities stored beside the tree)."""
    from nmjax.skeleton import load_skeleton, prune

    path = Path(run) / "skeleton.json"
    if not path.is_file():
        return None
    skeleton = load_skeleton(path)
    intensities = json.loads(path.read_text()).get("intensities")
    if intensities is None:
        return np.asarray(skeleton.parents), np.ones(skeleton.num_keypoints, bool)
    pruned, keep = prune(skeleton, intensities)
    return np.asarray(pruned.parents), keep


# --- interpolation M-CD -------------------------------------------------------------------------


def sequence_voxels(seq, sample_rate: int, grid: int) -> np.ndarray:
    """(S, G, G, G): every `sample_rate`-th frame, one bounding box over the whole sequence."""
    from nmjax.data.voxelize import normalize_sequence, voxelize

    points, _ = normalize_sequence(np.asarray(seq.vertices[::sample_rate], np.float32))
    return voxelize(points, grid)


def keyframe_starts(num_frames: int, rate: int, max_segments: int) -> np.ndarray:
    """Start keyframes ts = 0, SR, 2 SR, ... with ts + SR inside the sequence, at most M of them."""
    starts = np.arange(0, num_frames - rate, rate)
    if len(starts) > max_segments:
        starts = starts[np.linspace(0, len(starts) - 1, max_segments).astype(int)]
    return starts


@dataclasses.dataclass
class Interpolators:
    """The compiled interpolation methods on one phase-2 model (and the optional VRNN)."""

    nm: tuple[Any, Any]  # (graphdef, state) of the "nm" dynamics
    vrnn: tuple[Any, Any] | None
    trajectories: int

    def run(self, method: str, x_start, x_end, gap: int, key) -> np.ndarray:
        """(B, gap + 1, K, 4) keypoints of `method` between keyframes (B, K, 4)."""
        x_start, x_end = jnp.asarray(x_start), jnp.asarray(x_end)
        if method == "Lerp":
            return np.asarray(tasks.lerp_keypoints(x_start, x_end, gap))
        if method == "Slerp":
            return np.asarray(tasks.slerp_jit(*self.nm, x_start, x_end, key, gap=gap))
        model = self.nm if method == "Ours" else self.vrnn
        if model is None:
            raise ValueError(f"no model for method {method!r}")
        return np.asarray(
            tasks.interpolate_jit(
                *model, x_start[:, None], x_end, key, gap=gap, num_trajectories=self.trajectories
            )
        )


def evaluate_interpolation(
    detector: Detector,
    interpolators: Interpolators,
    trajectories: dict[str, np.ndarray],
    rates: tuple[int, ...] = SAMPLING_RATES,
    max_segments: int = 4,
    chunk: int = 4,
    seed: int = 0,
    split: str = "test",
    methods: tuple[str, ...] = METHODS,
    voxels: bool = True,
    keypoint_errors: dict | None = None,
) -> dict[str, dict[str, dict]]:
    """M-CD (Eq. 22) x1e3 of every method at every sampling rate, per test sequence.

    Alongside, when `keypoint_errors` is a dict it is filled in the same layout with the squared
    xyz error of the in-between keypoints against the observed ones (sum over K, mean over
    frames; a decoder-free check of the same interpolations).

    Args:
      detector: the phase-1 run's detector (its decoder turns keypoints into voxels).
      interpolators: the phase-2 models.
      trajectories: {sequence: (S, K, 4)} keypoints of `split` (keypoints_<split>.npz).
      rates: sampling rates SR (gap between keyframes, in sampled frames).
      max_segments: keyframe pairs per sequence and rate, spread over the sequence.
      chunk: keyframe pairs decoded at once (fixed, so each rate compiles once).
      seed: PRNG seed of the generative methods.
      split: the split whose sequences are evaluated.
      methods: the methods to run (VRNN is dropped when no VRNN model is given).
      voxels: decode and score M-CD; False computes only `keypoint_errors` (much faster).
      keypoint_errors: optional dict to receive the keypoint errors.

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
        if seq.name not in trajectories:
            raise ValueError(
                f"sequence {seq.name!r} of the {split} split has no keypoints in the phase-1 "
                f"run's keypoints_{split}.npz; re-export them with "
                f"`nmjax.train.skel.export_keypoints('{detector.run}', '{split}')`"
            )
        kp = trajectories[seq.name]
        vox = sequence_voxels(seq, cfg.data.sample_rate, cfg.data.grid)
        for rate in rates:
            starts = keyframe_starts(len(kp), rate, max_segments)
            if len(starts) == 0:
                continue  # the sequence is shorter than one gap
            scores: dict[str, list[float]] = {m: [] for m in methods}
            kp_err: dict[str, list[float]] = {m: [] for m in methods}
            for i in range(0, len(starts), chunk):
                ts = starts[i : i + chunk]
                ts = np.concatenate([ts, np.repeat(ts[-1:], chunk - len(ts))])  # fixed shape
                real = min(chunk, len(starts) - i)
                frames = ts[:, None] + np.arange(rate + 1)  # (chunk, SR + 1)
                key, sub = jax.random.split(key)
                for method in methods:
                    x = interpolators.run(method, kp[ts], kp[ts + rate], rate, sub)
                    inner = np.sum(
                        (x[:real, 1:-1, :, :3] - kp[frames[:real, 1:-1], :, :3]) ** 2, -1
                    )
                    kp_err[method] += list(np.mean(np.sum(inner, -1), -1)) if rate > 1 else []
                    if not voxels:
                        continue
                    recon = detector.decode(x, vox[ts])
                    for j in range(real):
                        mcd = metrics.motion_chamfer(vox[frames[j]], recon[j])
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


# --- tables and plots ---------------------------------------------------------------------------


def fmt(value: float, ci: float | None = None) -> str:
    """'1.23 (0.045)' with three significant digits; 'n/a' for NaN."""
    if value is None or not np.isfinite(value):
        return "n/a"
    text = f"{value:.3g}"
    return text if ci is None else f"{text} ({ci:.3g})" if np.isfinite(ci) else f"{text} (n/a)"


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


def plot_mcd(path: Path, mcd: dict, title: str = "") -> None:
    """M-CD against SR with 95% CI error bars, one line per method (Fig. 5 style)."""
    import matplotlib.pyplot as plt

    from nmjax.viz import save_figure  # selects the Agg backend

    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    for method, by_rate in mcd.items():
        rates = [int(r) for r in by_rate]
        means = np.array([by_rate[str(r)]["mean"] for r in rates])
        ci = np.nan_to_num(np.array([by_rate[str(r)]["ci95"] for r in rates]))
        ax.errorbar(rates, means, yerr=ci, marker="o", ms=3, capsize=3, label=method)
    ax.set_xlabel("sampling rate SR (frames between keyframes)")
    ax.set_ylabel("M-CD x1e3")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    save_figure(fig, path)


# --- the command ---------------------------------------------------------------------------------


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
    from nmjax.train import dyn

    run = Path(run)
    results: dict[str, Any] = {"run": str(run)}
    if run_kind(run) == "dyn":
        dyn_cfg = common.load_config(run, DynTrainConfig)
        if dyn_cfg.model.model != "nm":
            raise ValueError(
                f"{run} is a '{dyn_cfg.model.model}' run; give the Neural Marionette ('nm') run "
                "as --run and the positional baseline as --vrnn-run"
            )
        skel_run = Path(dyn_cfg.skel_run)
        if vrnn_run is None:
            vrnn_run = find_vrnn_run(run, skel_run)
        results["skel_run"] = str(skel_run)
        results["vrnn_run"] = None if vrnn_run is None else str(vrnn_run)
    else:
        skel_run, dyn_cfg = run, None
    detector = Detector.load(skel_run)
    results["phase1"] = evaluate_phase1(detector, max_crops=max_crops)
    if dyn_cfg is not None:
        nm = nnx.split(dyn.restore_model(run))
        vrnn = None if vrnn_run is None else nnx.split(dyn.restore_model(vrnn_run))
        traj = dyn.load_trajectories(skel_run, "test")
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
        )
        results["interpolation_keypoints"] = kp_errors
        results["settings"] = {
            "trajectories": trajectories,
            "max_segments": max_segments,
            "max_crops": max_crops,
            "seed": seed,
            "mcd_scale": MCD_SCALE,
        }
    out = Path(out) if out is not None else run / "eval"
    io.write_json(out / "results.json", results)
    io.write_text(out / "tables.md", markdown_tables(results))
    if "interpolation" in results:
        plot_mcd(out / "mcd.png", results["interpolation"], title=str(run.name))
    return results


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="nmjax evaluate",
        description="SC-score, 4D-tracking Chamfer and interpolation M-CD (paper Tables 1, 2, 11, "
        "12) of a phase-2 run (or the phase-1 metrics of a phase-1 run).",
    )
    parser.add_argument("--run", required=True, help="phase-2 ('nm') or phase-1 run folder")
    parser.add_argument("--vrnn-run", default=None, help="positional VRNN run (default: found)")
    parser.add_argument("--out", default=None, help="output folder (default RUN/eval)")
    parser.add_argument(
        "--rates", default=",".join(map(str, SAMPLING_RATES)), help="sampling rates SR"
    )
    parser.add_argument("--trajectories", type=int, default=16, help="rollouts per keyframe pair")
    parser.add_argument("--max-segments", type=int, default=4, help="keyframe pairs per sequence")
    parser.add_argument("--max-crops", type=int, default=8, help="phase-1 test crops per sequence")
    parser.add_argument("--seed", type=int, default=0)
    return parser.parse_args(argv)


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    try:
        rates = tuple(int(r) for r in args.rates.split(",") if r.strip())
        if not rates or min(rates) < 1:
            raise ValueError(f"--rates must be positive integers, got {args.rates!r}")
        for name in ("trajectories", "max_segments", "max_crops"):
            if getattr(args, name) < 1:
                raise ValueError(f"--{name.replace('_', '-')} must be >= 1")
        results = evaluate_run(
            args.run,
            vrnn_run=args.vrnn_run,
            out=args.out,
            rates=rates,
            trajectories=args.trajectories,
            max_segments=args.max_segments,
            max_crops=args.max_crops,
            seed=args.seed,
        )
    except (FileNotFoundError, ValueError) as err:
        print(f"nmjax evaluate: {err}", file=sys.stderr)
        return 1
    print(markdown_tables(results))
    return 0
