"""Phase-2 evaluation: interpolation M-CD (Eq. 22, Tables 11-12) of Ours, VRNN, Lerp and Slerp
at every sampling rate (`evaluate_interpolation`), and `evaluate_run`, the command that evaluates
a phase-2 run with every table (a phase-1 run with Tables 1-2) and writes them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
import numpy as np
from flax import nnx

from nmjax import atomic, metrics, provenance, run_folder
from nmjax.data.datasets import pad_with_last
from nmjax.evaluate.phase1 import PHASE1_METRICS, evaluate_phase1
from nmjax.evaluate.stats import summarize_per_rate
from nmjax.evaluate.tables import markdown_tables
from nmjax.tasks import INTERPOLATION_METHODS, Interpolators
from nmjax.train import dyn_inputs, trained
from nmjax.train.trained import Detector

SAMPLING_RATES = (3, 5, 10, 15, 20, 25, 30)
METHODS = INTERPOLATION_METHODS
MCD_SCALE = 1e3
INTERPOLATION_METRICS = {
    "interpolation": "M-CD (Eq. 22) x1e3, Tables 11-12: keypoints between keyframes SR frames "
    "apart decoded to voxels (phase-1 decoder, threshold 0.5), compared with the true voxels "
    "on difference voxels; mean and 95% CI over test sequences",
    "interpolation_keypoints": "squared xyz error of the in-between keypoints against the "
    "detector's, summed over K, mean over frames; mean and 95% CI over test sequences",
}


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
    kp = dyn_inputs.detect_clips(detector, clips, length)[:, : rate + 1]
    if not voxels:
        return kp, None
    vox = np.stack([dyn_inputs.clip_voxels(s, t, length, data)[: rate + 1] for s, t in clips])
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
    frames: int = 20,
) -> dict[str, dict[str, dict[str, dict]]]:
    """M-CD (Eq. 22) x1e3 of every method at every sampling rate, per test sequence, and beside
    it the squared xyz error of the in-between keypoints against the observed ones (sum over K,
    mean over frames; a decoder-free check of the same interpolations).

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
      voxels: decode and score M-CD; False computes only the keypoint errors (much faster).
      frames: T of phase 2, the shortest clip detected on "crop" inputs.

    Returns:
      {"interpolation": M-CD, "interpolation_keypoints": keypoint errors} (the keys of
      results.json), each {method: {str(SR): {"mean", "ci95", "n", "per_sequence"}}}; methods
      without a model left out, "interpolation" absent without `voxels`.
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
                    f"sequence {seq.name!r} of the {split} split has no keypoints in "
                    f"{run_folder.keypoints_file(detector.run, split)}; re-export them with "
                    f"`nmjax export-keypoints --run {detector.run}`"
                )
            vox = (
                trained.sequence_voxels(seq, cfg.data.sample_rate, cfg.data.grid)
                if voxels
                else None
            )
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
    tables = {"interpolation": summarize_per_rate(per_seq)} if voxels else {}
    return {**tables, "interpolation_keypoints": summarize_per_rate(kp_seq)}


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
    dyn = run_folder.run_kind(run) == "dyn"
    definitions = {**PHASE1_METRICS, **(INTERPOLATION_METRICS if dyn else {})}
    results: dict[str, Any] = {"provenance": provenance.stamp(definitions), "run": str(run)}
    if dyn:
        dyn_cfg, skel_run, vrnn_run = trained.phase2_runs(run, vrnn_run)
        results["skel_run"] = str(skel_run)
        results["vrnn_run"] = None if vrnn_run is None else str(vrnn_run)
    else:
        skel_run, dyn_cfg = run, None
    detector = Detector.load(skel_run).reading(None if dyn_cfg is None else dyn_cfg.data.root)
    results["phase1"] = evaluate_phase1(detector, max_crops=max_crops)
    if dyn_cfg is not None:
        nm = nnx.split(trained.restore_dynamics(run))
        vrnn = None if vrnn_run is None else nnx.split(trained.restore_dynamics(vrnn_run))
        traj = None
        if dyn_cfg.data.inputs == "sequence":
            traj = run_folder.load_trajectories(skel_run, "test")
        interp = Interpolators(nm, vrnn, trajectories)
        results |= evaluate_interpolation(
            detector,
            interp,
            traj,
            rates,
            max_segments=max_segments,
            seed=seed,
            frames=dyn_cfg.data.frames,
        )
        results["settings"] = {
            "trajectories": trajectories,
            "max_segments": max_segments,
            "max_crops": max_crops,
            "seed": seed,
            "mcd_scale": MCD_SCALE,
            "inputs": dyn_cfg.data.inputs,
        }
    out = Path(out) if out is not None else run / "eval"
    atomic.write_json(out / "results.json", results)
    provenance.write_markdown(out / "tables.md", markdown_tables(results), results["provenance"])
    if "interpolation" in results:
        from nmjax import viz  # matplotlib only where a picture is drawn

        viz.plot_mcd(out / "mcd.png", results["interpolation"], title=str(run.name))
        provenance.stamp_png(out / "mcd.png", results["provenance"])
    return results
