"""Generation evaluation (beyond the paper, which shows generation only as pictures): on
conditioning clips of T_cond test frames, S futures per clip from Ours, VRNN and the
hold-last-pose baseline, at each horizon N the diversity, the bone-length error of the generated
frames and the set distance to real test clips of N frames, with 95% confidence intervals over
clips (`evaluate_generation`); `evaluate_generation_run` is the command on a run folder.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from nmjax import atomic, metrics, provenance, run_folder, tasks
from nmjax.evaluate.stats import summarize
from nmjax.evaluate.tables import fmt
from nmjax.train import dyn_inputs, trained
from nmjax.train.trained import Detector

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
        (`trained.export_keypoints(..., data_root=...)`), so that long horizons have real clips.
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


def crop_conditioning(
    detector: Detector, clips: list[tuple[str, int]], cond: int, frames: int
) -> np.ndarray:
    """x_cond (B, cond, K, 4) of conditioning clips as the release's generation takes it.

    Each clip (sequence, start in sampled frames) is its first crop, max(T, cond) frames,
    normalised with its own bounding box; its first `cond` frames go through the detector on
    their own (`dyn_inputs.detect_clips`).
    """
    seqs, rate = dyn_inputs.split_sequences(detector, "test"), detector.cfg.data.sample_rate
    located = [(seqs[name], start * rate) for name, start in clips]
    return dyn_inputs.detect_clips(detector, located, max(frames, cond), detect=cond)


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
    if run_folder.run_kind(run) != "dyn":
        raise ValueError(
            f"{run} is a phase-1 run; --generation needs a phase-2 'nm' run (nmjax train-dyn)"
        )
    dyn_cfg, skel_run, vrnn_run = trained.phase2_runs(run, vrnn_run)
    skeleton = run_folder.pruned_skeleton(skel_run)
    if skeleton is None:
        raise FileNotFoundError(
            f"{skel_run}/skeleton.json not found; run `nmjax extract-skeleton --run {skel_run}`"
        )
    trajectories = run_folder.load_trajectories(skel_run, "test")
    conditioning = None
    if dyn_cfg.data.inputs == "crop":
        names, _ = conditioning_clips(trajectories, cond, clips)
        x_cond = crop_conditioning(
            dyn_inputs.phase2_detector(skel_run, dyn_cfg.data.root),
            names,
            cond,
            dyn_cfg.data.frames,
        )
        conditioning = (names, x_cond)
    models = {"Ours": nnx.split(trained.restore_dynamics(run))}
    if vrnn_run is not None:
        models["VRNN"] = nnx.split(trained.restore_dynamics(vrnn_run))
    settings = {"horizons": list(horizons), "cond": cond, "samples": samples, "clips": clips}
    settings["inputs"] = dyn_cfg.data.inputs
    real = None
    if real_keypoints is not None:
        real = run_folder.read_trajectories(Path(real_keypoints))
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
