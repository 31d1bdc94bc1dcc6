"""The paper's phase-1 results at the `cpu` preset on the four synthetic bodies, a row per run.

    JAX_PLATFORMS=cpu .venv/bin/python experiments/paper_phase1.py \
        [--data synth-arm synth-hand synth-human synth-quadruped] [--seeds 0 1] \
        [--groups preset comparisons alternative] [--steps N] [--dry-run]

A row is one phase-1 run of (body, seed, variant), trained into `runs/exp/skel-<body>-s<seed>-
<variant>` and scored on the test split:

- preset:  the `cpu` preset (Tables 1 and 2), every body at every seed;
- gt:      L_vol replaced by the MSE to the ground-truth joints, K = J (Table 2's supervised
           baseline), seed 0 on the bodies standing for the paper's ablation datasets
           (synth-human for AIST++, synth-hand for HanCo);
- no_vol:  w_vol = 0 (Tables 9-10), the same bodies and seed;
- no_traj: w_traj = 0 (appendix C.2), the same;
- fan_in:  `model.init=fan_in`, the preset's one named alternative, seed 0 on every body and
           seed 1 on the bodies where seed 0 favours it (lower joint distance and more distinct
           nodes than the preset at seed 0).

Each row holds the test scores of `nmjax.evaluate.evaluate_phase1` (SC in both definitions,
tracking CD x1e4 with its CI, bone-length variation, the skeleton against the ground truth),
Algorithm 1 against the filtered rule on the run's affinity (`alg1_vs_filtered`), the pruned
tree, one test frame for the pictures (keypoints and a sample of the occupied cells), the wall
time, the configuration and the `nmjax.provenance` stamp of the code that trained and scored it.
Rows accumulate in `experiments/results/phase1_rows.json`, written as soon as each run is scored
(commit it then: run folders do not survive a new machine); `phase1_tables.py` renders every
table and figure from that file after each row.

A row already in the file is kept, and its run not trained again, when it was made by code that
computes the same thing: the same configuration (config.json, the run folder's path aside), the
same metric definitions, and a commit that descends from `PHASE1_SINCE`, the last commit that
changed what a phase-1 run trains or how it is scored (move it forward with any such change, and
the rows made before it are made again). A dirty checkout's row is never kept.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import time
from pathlib import Path
from typing import Any

import exp_common as ec
import numpy as np
import phase1_tables

from nmjax import provenance, run_folder
from nmjax.config import SkelTrainConfig, skel_preset, with_steps
from nmjax.config_io import config_from_dict, config_to_dict
from nmjax.evaluate import (
    PHASE1_METRICS,
    evaluate_phase1,
    phase1_outputs,
    phase1_scores,
    skeleton_against_truth,
    true_tree,
)
from nmjax.metrics import voxel_points
from nmjax.skeleton import extract_skeleton, prune
from nmjax.train import skel
from nmjax.train.trained import Detector

BODIES, COMPARISON_BODIES = phase1_tables.BODIES, phase1_tables.COMPARISON_BODIES
VARIANTS = {
    "preset": "the cpu preset",
    "gt": "L_vol replaced by the MSE to the ground-truth joints, K = J (Table 2's GT)",
    "no_vol": "w_vol = 0 (Tables 9-10)",
    "no_traj": "w_traj = 0 (appendix C.2)",
    "fan_in": "model.init=fan_in (the cpu preset's named alternative)",
}
GROUPS = ("preset", "comparisons", "alternative")
ROWS_FILE = ec.RESULTS / "phase1_rows.json"
# The last commit that changed what a phase-1 run trains or how it is scored: the release's
# heatmap and cosine conventions.
PHASE1_SINCE = "648c59456ea81d1abf8f60e70e3d2dc4bb930c9a"
# Minutes a row is expected to take before any row of this machine has been timed.
DEFAULT_ROW_MINUTES = 30.0
# Test crops per sequence for the scores, and occupied cells kept per row for the pictures.
MAX_CROPS = 8
PICTURE_POINTS = 1500
METRICS = {
    **PHASE1_METRICS,
    "alg1_vs_filtered": "edge precision (within 2 hops) and bone recall of the tree of "
    "Algorithm 1 and of the filtered rule (`nmjax.skeleton.extract_skeleton`), each pruned at "
    "the run's threshold, on the same test keypoints",
}


@dataclasses.dataclass(frozen=True)
class RowKey:
    body: str
    seed: int
    variant: str

    @property
    def name(self) -> str:
        return f"{self.body}-s{self.seed}-{self.variant}"

    @classmethod
    def of(cls, row: dict[str, Any]) -> RowKey:
        return cls(row["body"], int(row["seed"]), row["variant"])


def row_config(key: RowKey, steps: int | None = None) -> SkelTrainConfig:
    """The phase-1 configuration of a row: the `cpu` preset at the row's seed (model and data
    order), with the variant's one change; `steps` replaces the preset's length (smoke runs)."""
    cfg = skel_preset(key.body, "cpu")
    cfg = dataclasses.replace(
        cfg,
        seed=key.seed,
        data=dataclasses.replace(cfg.data, seed=key.seed),
        run=str(row_run_dir(key)),
    )
    if steps is not None:
        cfg = with_steps(cfg, steps)
    if key.variant == "gt":
        cfg = ec.supervised_by_joints(cfg, key.body)
    elif key.variant == "no_vol":
        cfg = dataclasses.replace(cfg, weights=dataclasses.replace(cfg.weights, vol=0.0))
    elif key.variant == "no_traj":
        cfg = dataclasses.replace(cfg, weights=dataclasses.replace(cfg.weights, traj=0.0))
    elif key.variant == "fan_in":
        cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, init="fan_in"))
    elif key.variant != "preset":
        raise ValueError(f"unknown variant {key.variant!r}; valid: {', '.join(VARIANTS)}")
    return cfg


def row_run_dir(key: RowKey) -> Path:
    return ec.RUNS / f"skel-{key.name}"


def comparable(config: dict[str, Any]) -> dict[str, Any]:
    """A config.json without what does not change the computation (the run folder's path) or
    is filled in from the data when training starts (steps_per_epoch), as JSON reads it back.

    Read through the configuration's dataclass first: a field added since the row was stored
    reads as its default (what the row's code computed), as `nmjax.run_folder.load_config`
    reads an older run's config.json.
    """
    try:
        config = config_to_dict(config_from_dict(SkelTrainConfig, config))
    except (ValueError, TypeError):  # a field since removed: compared as stored, so unequal
        pass
    config = {k: v for k, v in config.items() if k != "run"}
    if isinstance(config.get("loop"), dict):
        config["loop"] = {k: v for k, v in config["loop"].items() if k != "steps_per_epoch"}
    return json.loads(json.dumps(config))


def descends_from(commit: str | None, ancestor: str = PHASE1_SINCE) -> bool:
    """Whether `commit` is `ancestor` or one of its descendants in this clone's history."""
    if not commit:
        return False
    done = subprocess.run(
        ["git", "merge-base", "--is-ancestor", ancestor, commit],
        cwd=Path(__file__).parent,
        capture_output=True,
    )
    return done.returncode == 0


def same_computation(row: dict[str, Any], cfg: SkelTrainConfig) -> bool:
    """Whether a stored row was made by code that computes what `cfg` would now (module doc)."""
    stamp = row.get("provenance", {})
    return (
        comparable(row.get("config", {})) == comparable(config_to_dict(cfg))
        and stamp.get("metrics") == METRICS
        and stamp.get("dirty") is False
        and descends_from(stamp.get("commit"))
    )


def read_rows(path: Path = ROWS_FILE) -> list[dict[str, Any]]:
    return json.loads(path.read_text())["rows"] if path.is_file() else []


def write_rows(rows: list[dict[str, Any]], stamp: dict[str, Any], path: Path = ROWS_FILE):
    order = {name: i for i, name in enumerate(VARIANTS)}
    rows = sorted(rows, key=lambda r: (order[r["variant"]], r["seed"], r["body"]))
    provenance.write_json(path, {"metrics": METRICS, "rows": rows}, stamp)


def plan(
    bodies: list[str], seeds: list[int], groups: list[str], rows: list[dict[str, Any]]
) -> list[RowKey]:
    """Every row of `groups` on `bodies` and `seeds`, in the order they are trained: the preset
    seed by seed, the comparisons, the alternative (its seed 1 only where seed 0 favours it)."""
    keys = []
    if "preset" in groups:
        keys += [RowKey(b, s, "preset") for s in seeds for b in bodies]
    if "comparisons" in groups and 0 in seeds:
        for variant in phase1_tables.COMPARISONS:
            keys += [RowKey(b, 0, variant) for b in COMPARISON_BODIES if b in bodies]
    if "alternative" in groups:
        keys += [RowKey(b, 0, "fan_in") for b in bodies if 0 in seeds]
        keys += [
            RowKey(b, 1, "fan_in")
            for b in bodies
            if 1 in seeds and phase1_tables.favours_alternative(rows, b) is not False
        ]
    return keys


def complete(run: Path, cfg: SkelTrainConfig) -> bool:
    """Whether `run` holds a finished run of `cfg` with its skeleton."""
    finished = ec.finished(run, cfg, comparable)
    return finished is not None and (run / run_folder.SKELETON_FILE).is_file()


def train(key: RowKey, cfg: SkelTrainConfig) -> tuple[Path, float | None]:
    """The finished run folder of a row (trained now, or resumed, unless already complete) and
    the minutes this call spent training it (None when it was already complete)."""
    run = row_run_dir(key)
    if complete(run, cfg):
        return run, None
    tic = time.perf_counter()
    resumable = (run / run_folder.CONFIG_FILE).is_file() and comparable(
        json.loads((run / run_folder.CONFIG_FILE).read_text())
    ) == comparable(config_to_dict(cfg))
    has_checkpoint = resumable and bool(run_folder.checkpoint_steps(run))
    cfg = dataclasses.replace(cfg, run=str(run))
    skel.train_skeleton(cfg, resume=has_checkpoint, overwrite=not has_checkpoint, progress=True)
    return run, (time.perf_counter() - tic) / 60


def picture_frame(detector: Detector) -> dict[str, Any]:
    """One test frame for the pictures: the middle frame of the first test crop's keypoints and
    a fixed sample of its occupied cells (rounded to 1e-3, the grid's scale is 1/16)."""
    _, voxels, _, keypoints, _ = next(iter(phase1_outputs(detector, max_crops=1)))
    t = voxels.shape[1] // 2
    cells = voxel_points(voxels[0, t])
    if len(cells) > PICTURE_POINTS:
        cells = cells[np.random.default_rng(0).choice(len(cells), PICTURE_POINTS, replace=False)]
    return {
        "keypoints": np.round(keypoints[0, t], 4).tolist(),
        "points": np.round(cells, 3).tolist(),
    }


def alg1_vs_filtered(detector: Detector, max_crops: int) -> dict[str, dict[str, float]] | None:
    """Edge precision (within 2 hops) and bone recall of both tree rules on the run's affinity
    and mean intensities, pruned at the run's threshold, on the same test keypoints."""
    run = detector.run
    stored = json.loads((run / run_folder.SKELETON_FILE).read_text())
    affinity, stats = run_folder.read_skeleton_inputs(run)
    names, keypoints, joints = [], [], []
    for name, _, gt, kp, _ in phase1_outputs(detector, max_crops):
        if gt is None:
            return None
        names.append(name)
        keypoints.append(kp)
        joints.append(gt)
    truth = true_tree(detector, joints[0].shape[-2])
    if truth is None:
        return None
    out = {}
    for method in ("algorithm1", "filtered"):
        tree = extract_skeleton(
            affinity, stored["n_neighbors"], stats["intensities"], method=method
        )
        pruned, keep = prune(tree, stats["intensities"], stored["prune_threshold"])
        scores = skeleton_against_truth(
            keypoints, joints, (np.asarray(pruned.parents), keep), truth, names
        )
        out[method] = {
            k: scores[k] for k in ("edge_precision", "edge_precision_within_2_hops", "bone_recall")
        }
        out[method]["parents"] = [int(p) for p in pruned.parents]
    return out


def score(key: RowKey, run: Path, cfg: SkelTrainConfig, minutes, stamp) -> dict[str, Any]:
    """The row of a finished run (see the module docstring)."""
    detector = Detector.load(run)
    results = evaluate_phase1(detector, MAX_CROPS)
    scores = phase1_scores(results)
    parents, keep = run_folder.pruned_skeleton(run)
    return {
        "body": key.body,
        "seed": key.seed,
        "variant": key.variant,
        "run": str(run),
        "train_minutes": minutes,
        "steps": cfg.loop.steps,
        "scores": scores,
        "per_sequence": {
            "tracking_cd": results["tracking"]["per_sequence"],
            **({"sc": results["sc"]["per_sequence"]} if "sc" in results else {}),
        },
        "pruned_parents": parents.tolist(),
        "keep": keep.tolist(),
        "alg1_vs_filtered": alg1_vs_filtered(detector, MAX_CROPS),
        "frame": picture_frame(detector),
        "config": json.loads((run / run_folder.CONFIG_FILE).read_text()),  # as it trained
        "provenance": stamp,
    }


def estimate_minutes(rows: list[dict[str, Any]], todo: list[RowKey]) -> float:
    """Expected wall minutes of `todo`: per body the median of its rows' measured training time
    on this kind of CPU, else of every such row, else `DEFAULT_ROW_MINUTES`."""
    cpu = provenance.cpu_model()
    timed = [r for r in rows if r.get("train_minutes") and r["provenance"].get("cpu") == cpu]
    everyone = float(np.median([r["train_minutes"] for r in timed])) if timed else None
    total = 0.0
    for key in todo:
        own = [r["train_minutes"] for r in timed if r["body"] == key.body]
        total += float(np.median(own)) if own else (everyone or DEFAULT_ROW_MINUTES)
    return total


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", nargs="+", default=list(BODIES), choices=BODIES)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    parser.add_argument("--groups", nargs="+", default=list(GROUPS), choices=GROUPS)
    parser.add_argument(
        "--steps", type=int, default=None, help="steps per run instead of the preset's (smoke)"
    )
    parser.add_argument("--rows", type=Path, default=ROWS_FILE, help="the rows file")
    parser.add_argument("--dry-run", action="store_true", help="print the plan and stop")
    parser.add_argument(
        "--allow-dirty", action="store_true", help="train even with uncommitted changes"
    )
    args = parser.parse_args(argv)
    rows = read_rows(args.rows)

    made: set[RowKey] = set()  # this call's rows, each made once

    def pending() -> list[tuple[RowKey, SkelTrainConfig]]:
        out = []
        for key in plan(args.data, args.seeds, args.groups, rows):
            if key in made:
                continue
            cfg = row_config(key, args.steps)
            kept = [r for r in rows if RowKey.of(r) == key and same_computation(r, cfg)]
            if not kept:
                out.append((key, cfg))
        return out

    todo = pending()
    planned = plan(args.data, args.seeds, args.groups, rows)
    print(
        f"{len(todo)} rows to make ({', '.join(k.name for k, _ in todo) or 'none'}); "
        f"{len(planned) - len(todo)} of the plan already made; estimated "
        f"{estimate_minutes(rows, [k for k, _ in todo]):.0f} min of training on this machine",
        flush=True,
    )
    if args.dry_run or not todo:
        return
    ec.refuse_dirty("paper_phase1", args.allow_dirty)
    while todo:
        key, cfg = todo[0]
        stamp = provenance.stamp(METRICS)
        print(f"--- {key.name}: training into {row_run_dir(key)}", flush=True)
        run, minutes = train(key, cfg)
        row = score(key, run, cfg, minutes, stamp)
        made.add(key)
        rows = [r for r in rows if RowKey.of(r) != key] + [row]
        write_rows(rows, stamp, args.rows)
        phase1_tables.render(rows, args.rows.parent)
        s = row["scores"]
        print(
            f"--- {key.name}: SC {s.get('sc', float('nan')):.3f}, CD {s['tracking_cd']:.1f}, "
            f"joint distance {s.get('joint_distance', float('nan')):.3f}, distinct "
            f"{s.get('distinct_nodes', 'n/a')} of {s.get('skeleton_kept_nodes', 'n/a')} kept; "
            f"row written to {args.rows}",
            flush=True,
        )
        todo = pending()  # the alternative's seed-1 rows depend on its seed-0 rows


if __name__ == "__main__":
    main()
