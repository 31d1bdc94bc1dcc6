"""The paper's phase-2 results at the `cpu` preset on the four synthetic bodies, a row per body.

    JAX_PLATFORMS=cpu .venv/bin/python experiments/paper_phase2.py \
        [--data synth-arm synth-hand synth-human synth-quadruped] [--steps N] [--dry-run]

A row is phase 2 on one body's phase-1 row of `paper_phase1.py` (the `cpu` preset at seed 0; its
run folder is trained again when missing): Ours (the released dynamics model, "nm") and the
positional VRNN baseline, each trained at the `cpu` preset on the release's crop inputs into
`runs/exp/dyn-<body>-<model>`, then scored on the test split:

- interpolation: M-CD x1e3 at SR 3..30 of Ours, VRNN, Lerp and Slerp, and the decoder-free
  in-between keypoint error (`nmjax.evaluate.evaluate_run`; Tables 11-12);
- generation: diversity, bone-length error and set distance to real motion of Ours, VRNN and
  hold-last-pose at N = 25 / 100 / 300 (`nmjax.evaluate.evaluate_generation_run`);
- both models' learning curves (metrics.jsonl), final validation and speed.

Rows accumulate in `experiments/results/phase2_rows.json`, written as soon as each body is
scored (commit it then: run folders do not survive a new machine); `phase2_tables.py` renders
every table and figure from that file after each row.

A row already in the file is kept, and its runs not trained again, when it was made by code that
computes the same thing: the same two phase-2 configurations (config.json, the run folders'
paths aside), the same evaluation settings and metric definitions, the same phase-1 row (its
name and the commit that made it, which `paper_phase1.py` itself keeps or remakes), and a commit
that descends from `PHASE2_SINCE`, the last commit that changed what a phase-2 run trains or how
it is scored (move it forward with any such change). A dirty checkout's row is never kept.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import time
from pathlib import Path
from typing import Any

import exp_common as ec
import jax
import numpy as np
import paper_phase1
import phase2_tables

from nmjax import provenance, run_folder
from nmjax.config import DynTrainConfig, dyn_preset
from nmjax.config_io import config_from_dict, config_to_dict, replace_fields
from nmjax.evaluate import (
    GEN_HORIZONS,
    GENERATION_METRICS,
    INTERPOLATION_METRICS,
    SAMPLING_RATES,
    evaluate_generation_run,
    evaluate_run,
)
from nmjax.train import dyn, metric_log

BODIES = phase2_tables.BODIES
MODELS = tuple(phase2_tables.MODELS)
# The phase-2 network, inputs and conventions of the release (the GRU's four gate biases, the
# decoder's output as the 6D vector, the release's 6D -> rotation).
PHASE2_SINCE = "74aee1f7ef8c19f266190d8fd8e7115c30d97849"
ROWS_FILE = ec.RESULTS / "phase2_rows.json"
# The evaluation of every row (each is a setting of evaluate_run / evaluate_generation_run).
SETTINGS = {
    "rates": list(SAMPLING_RATES),
    "trajectories": 16,
    "max_segments": 4,
    "horizons": list(GEN_HORIZONS),
    "samples": 10,
    "cond": 5,
    "clips": 4,
    "seed": 0,
}
METRICS = {
    **INTERPOLATION_METRICS,
    **GENERATION_METRICS,
    "curves": "metrics.jsonl of each phase-2 run as logged (train/* every log_every steps, "
    "val/* every val_every steps: the validation of `nmjax train-dyn`)",
    "steps_per_s_median": "median of the logged training steps/s, the first left out",
}
DEFAULT_ROW_MINUTES = 20.0


def dyn_run_dir(body: str, model: str) -> Path:
    return ec.RUNS / f"dyn-{body}-{model}"


def dyn_config(body: str, model: str, skel: Path, steps: int | None = None) -> DynTrainConfig:
    """The phase-2 configuration of `model` on the phase-1 run `skel`: the `cpu` preset;
    `steps` replaces its length (smoke runs)."""
    cfg = dyn_preset(body, "cpu")
    cfg = dataclasses.replace(
        cfg,
        skel_run=str(skel),
        run=str(dyn_run_dir(body, model)),
        model=dataclasses.replace(cfg.model, model=model),
    )
    return cfg if steps is None else replace_fields(cfg, steps=steps)


def comparable(config: dict[str, Any]) -> dict[str, Any]:
    """A phase-2 config.json without the run folders' paths (the phase-1 row is compared by its
    name and commit instead) and what is filled in from the data when training starts
    (steps_per_epoch), read through the dataclass so that a field added since the row was
    stored reads as its default, as JSON reads it back."""
    try:
        config = config_to_dict(config_from_dict(DynTrainConfig, config))
    except (ValueError, TypeError):  # a field since removed: compared as stored, so unequal
        pass
    config = {k: v for k, v in config.items() if k not in ("run", "skel_run")}
    if isinstance(config.get("loop"), dict):
        config["loop"] = {k: v for k, v in config["loop"].items() if k != "steps_per_epoch"}
    return json.loads(json.dumps(config))


def phase1_source(
    phase1_rows: list[dict[str, Any]], body: str, allow_dirty: bool = False
) -> dict[str, Any] | None:
    """The phase-1 row phase 2 of `body` trains on (seed 0, preset) as `paper_phase1.py` would
    keep it, as {"row", "commit", "run"}; None when it is not made (or would be made again).
    `allow_dirty` also takes a row made from a dirty checkout (whose phase-2 row is then dirty
    too, so never kept)."""
    key = paper_phase1.RowKey(body, 0, "preset")
    cfg = paper_phase1.row_config(key)
    for row in phase1_rows:
        if allow_dirty:
            row = {**row, "provenance": {**row.get("provenance", {}), "dirty": False}}
        if paper_phase1.RowKey.of(row) == key and paper_phase1.same_computation(row, cfg):
            return {"row": key.name, "commit": row["provenance"]["commit"], "run": row["run"]}
    return None


def same_computation(
    row: dict[str, Any], configs: dict[str, DynTrainConfig], phase1: dict[str, Any]
) -> bool:
    """Whether a stored row was made by code that computes what `configs` on the phase-1 row
    `phase1` would now (module docstring)."""
    stamp = row.get("provenance", {})
    stored = row.get("models", {})
    return (
        set(stored) == set(configs)
        and all(
            comparable(stored[m].get("config", {})) == comparable(config_to_dict(cfg))
            for m, cfg in configs.items()
        )
        and row.get("settings") == SETTINGS
        and {k: row.get("phase1", {}).get(k) for k in ("row", "commit")}
        == {k: phase1[k] for k in ("row", "commit")}
        and stamp.get("metrics") == METRICS
        and stamp.get("dirty") is False
        and paper_phase1.descends_from(stamp.get("commit"), PHASE2_SINCE)
    )


def complete(run: Path, cfg: DynTrainConfig) -> bool:
    """Whether `run` holds a finished run of `cfg` on the same phase-1 run folder."""
    finished = ec.finished(run, cfg, comparable)
    return finished is not None and finished.get("skel_run") == cfg.skel_run


def train(cfg: DynTrainConfig) -> tuple[Path, float | None]:
    """The finished run folder of `cfg` (trained now, from the start, unless already complete:
    a phase-2 run at the cpu preset takes minutes, so an interrupted one is not resumed) and the
    minutes this call spent training it (None when it was already complete)."""
    run = Path(cfg.run)
    if complete(run, cfg):
        return run, None
    if run.exists():
        shutil.rmtree(run)
    tic = time.perf_counter()
    dyn.train_dynamics(cfg, progress=True)
    return run, (time.perf_counter() - tic) / 60


def release_compiled_programs() -> None:
    """Drops JAX's compiled programs between the stages of a row. On CPU each one holds a few
    memory mappings of machine code until released, and the training and scoring of several
    bodies in one process compile enough of them to pass the kernel's limit on mappings per
    process (vm.max_map_count, 65,530 by default), where XLA's next compilation fails ("Cannot
    allocate memory") and the process dies: it happened on the third body of one run."""
    jax.clear_caches()


def model_record(run: Path, minutes: float | None) -> dict[str, Any]:
    """What a row keeps of one trained phase-2 run: its config as trained, the curves, the last
    validation and the training speed."""
    records = metric_log.read_metrics(run)
    rates = [r["train/steps_per_s"] for r in records if "train/steps_per_s" in r][1:]
    validation = [r for r in records if "val/recon" in r]
    return {
        "run": str(run),
        "config": json.loads((run / run_folder.CONFIG_FILE).read_text()),
        "train_minutes": minutes,
        "final_validation": validation[-1] if validation else None,
        "steps_per_s_median": float(np.median(rates)) if rates else None,
        "curve": records,
    }


def score(
    body: str, phase1: dict[str, Any], trained: dict[str, tuple[Path, float | None]], stamp
) -> dict[str, Any]:
    """The row of a body whose two phase-2 runs are trained (module docstring)."""
    nm, vrnn = trained["nm"][0], trained["vrnn"][0]
    out = ec.RUNS / f"eval-{body}"
    tic = time.perf_counter()
    interp = evaluate_run(
        nm,
        vrnn_run=vrnn,
        out=out,
        rates=tuple(SETTINGS["rates"]),
        trajectories=SETTINGS["trajectories"],
        max_segments=SETTINGS["max_segments"],
        max_crops=1,  # the phase-1 tables are the phase-1 rows'; one crop keeps this cheap
        seed=SETTINGS["seed"],
    )
    release_compiled_programs()
    gen = evaluate_generation_run(
        nm,
        vrnn_run=vrnn,
        out=out,
        horizons=tuple(SETTINGS["horizons"]),
        cond=SETTINGS["cond"],
        samples=SETTINGS["samples"],
        clips=SETTINGS["clips"],
        seed=SETTINGS["seed"],
    )
    return {
        "body": body,
        "phase1": phase1,
        "models": {m: model_record(run, minutes) for m, (run, minutes) in trained.items()},
        "interpolation": interp["interpolation"],
        "interpolation_keypoints": interp["interpolation_keypoints"],
        "generation": {k: v for k, v in gen.items() if k != "provenance"},
        "settings": SETTINGS,
        "eval_minutes": (time.perf_counter() - tic) / 60,
        "provenance": stamp,
    }


def read_rows(path: Path = ROWS_FILE) -> list[dict[str, Any]]:
    return json.loads(path.read_text())["rows"] if path.is_file() else []


def write_rows(rows: list[dict[str, Any]], stamp: dict[str, Any], path: Path = ROWS_FILE):
    order = {b: i for i, b in enumerate(BODIES)}
    rows = sorted(rows, key=lambda r: order.get(r["body"], len(order)))
    provenance.write_json(path, {"metrics": METRICS, "settings": SETTINGS, "rows": rows}, stamp)


def estimate_minutes(rows: list[dict[str, Any]], todo: int) -> float:
    """Expected wall minutes of `todo` rows: the median of the measured rows (training and
    scoring) on this kind of CPU, else `DEFAULT_ROW_MINUTES`."""
    cpu = provenance.cpu_model()
    timed = [
        r["eval_minutes"] + sum(m["train_minutes"] or 0 for m in r["models"].values())
        for r in rows
        if r["provenance"].get("cpu") == cpu
        and all(m["train_minutes"] for m in r["models"].values())
    ]
    return todo * (float(np.median(timed)) if timed else DEFAULT_ROW_MINUTES)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", nargs="+", default=list(BODIES), choices=BODIES)
    parser.add_argument(
        "--steps", type=int, default=None, help="phase-2 steps instead of the preset's (smoke)"
    )
    parser.add_argument("--rows", type=Path, default=ROWS_FILE, help="the rows file")
    parser.add_argument(
        "--phase1-rows", type=Path, default=paper_phase1.ROWS_FILE, help="paper_phase1's rows"
    )
    parser.add_argument("--dry-run", action="store_true", help="print the plan and stop")
    parser.add_argument(
        "--allow-dirty",
        action="store_true",
        help="train even with uncommitted changes, also on phase-1 rows made that way (the rows "
        "made are never kept)",
    )
    args = parser.parse_args(argv)
    rows = read_rows(args.rows)
    phase1_rows = paper_phase1.read_rows(args.phase1_rows)
    todo, waiting = [], []
    for body in args.data:
        phase1 = phase1_source(phase1_rows, body, args.allow_dirty)
        if phase1 is None:
            waiting.append(body)
            continue
        configs = {m: dyn_config(body, m, Path(phase1["run"]), args.steps) for m in MODELS}
        if not any(r["body"] == body and same_computation(r, configs, phase1) for r in rows):
            todo.append((body, phase1, configs))
    print(
        f"{len(todo)} rows to make ({', '.join(b for b, _, _ in todo) or 'none'}); "
        f"{len(args.data) - len(todo) - len(waiting)} already made"
        + (f"; waiting for the phase-1 row of {', '.join(waiting)}" if waiting else "")
        + f"; estimated {estimate_minutes(rows, len(todo)):.0f} min on this machine",
        flush=True,
    )
    if args.dry_run or not todo:
        return
    ec.refuse_dirty("paper_phase2", args.allow_dirty)
    for body, phase1, configs in todo:
        stamp = provenance.stamp(METRICS)
        # The phase-1 run again when its folder did not come with the rows (a new machine).
        key = paper_phase1.RowKey(body, 0, "preset")
        skel, _ = paper_phase1.train(key, paper_phase1.row_config(key))
        if str(skel) != phase1["run"]:
            raise SystemExit(
                f"paper_phase2: {key.name} trains into {skel}, its row says {phase1['run']}"
            )
        trained = {}
        for model, cfg in configs.items():
            print(f"--- {body} {model}: training into {cfg.run}", flush=True)
            trained[model] = train(cfg)
            release_compiled_programs()
        print(f"--- {body}: scoring interpolation and generation", flush=True)
        row = score(body, phase1, trained, stamp)
        rows = [r for r in rows if r["body"] != body] + [row]
        write_rows(rows, stamp, args.rows)
        phase2_tables.render(rows, args.rows.parent)
        average = {m: phase2_tables.average(v) for m, v in row["interpolation"].items()}
        print(
            f"--- {body}: M-CD averages "
            + ", ".join(f"{m} {v:.3f}" for m, v in average.items())
            + f"; row written to {args.rows}",
            flush=True,
        )


if __name__ == "__main__":
    main()
