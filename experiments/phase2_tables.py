"""Every phase-2 table and picture of the paper's results, rendered from the rows of
`paper_phase2.py` (`experiments/results/phase2_rows.json`); nothing is trained or scored here.

    .venv/bin/python experiments/phase2_tables.py [--rows experiments/results/phase2_rows.json]

Writes beside the rows file, each `.md` and `.json` stamped by `nmjax.provenance` (the renderer's
commit; every row names the commit that trained and scored it):

- train_dyn_<body>:          phase 2's learning curves of Ours ("nm") and the positional VRNN
                             on the body's phase-1 row, their final validation and speed;
- table11_12_interpolation:  interpolation M-CD x1e3 at SR 3..30 of Ours, VRNN, Lerp and Slerp
                             per body (Tables 11-12), with table11_12_<body>.png, and the
                             decoder-free in-between keypoint error (table11_12_keypoints.md);
- generation_<body>:         diversity, bone-length error, set distance and hold-last-pose at
                             N = 25 / 100 / 300.

A table whose rows are not all made yet says which are missing.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import phase1_tables

from nmjax import provenance, viz
from nmjax.config import DynTrainConfig
from nmjax.config_io import config_from_dict
from nmjax.evaluate import REFERENCE, fmt, generation_tables, interpolation_table

BODIES = phase1_tables.BODIES
MODELS = {"nm": "Ours", "vrnn": "VRNN (positional)"}
PAPER_MCD = (
    "Paper Table 11 (HanCo) averages: Ours 2.64, VRNN 2.98, Lerp 5.07, Slerp 4.52; Table 12 "
    "(D-FAUST): Ours 2.88, VRNN 2.96, Lerp 3.67, Slerp 3.65 (scale not stated in the paper)."
)


def _commit(row: dict[str, Any]) -> str:
    stamp = row["provenance"]
    return (stamp.get("commit") or "unknown")[:7] + ("+dirty" if stamp.get("dirty") else "")


def _config(model: dict[str, Any]) -> DynTrainConfig:
    """A row's phase-2 configuration as trained, whichever config.json layout it was stored in."""
    return config_from_dict(DynTrainConfig, model["config"])


def _made_by(row: dict[str, Any]) -> str:
    """One markdown line: what a row was trained on and by which code."""
    p1 = row["phase1"]
    models = ", ".join(
        f"{MODELS[m]} `{info['run']}` {_config(info).loop.steps} steps"
        + (f" ({info['train_minutes']:.1f} min)" if info.get("train_minutes") else "")
        for m, info in row["models"].items()
    )
    return (
        f"phase 1: row {p1['row']} (`{p1['run']}`, commit {p1['commit'][:7]}); phase 2 "
        f"(`cpu` preset, inputs {_config(row['models']['nm']).data.inputs}): {models}; "
        f"trained and scored at {_commit(row)}"
    )


def _missing(rows: list[dict[str, Any]], bodies: tuple[str, ...]) -> str:
    made = {r["body"] for r in rows}
    gone = [b for b in bodies if b not in made]
    return f"Not made yet: {', '.join(gone)}.\n" if gone else ""


def average(by_rate: dict[str, dict[str, Any]]) -> float:
    """The mean over sampling rates of one method's M-CD (Tables 11-12's "Average" column)."""
    means = [e["mean"] for e in by_rate.values() if math.isfinite(e["mean"])]
    return float(np.mean(means)) if means else math.nan


def interpolation_ordering(mcd: dict[str, dict[str, dict[str, Any]]]) -> str:
    """One sentence on the paper's ordering (Ours below Lerp and Slerp, and below the VRNN) read
    off the averages and the rates where the 95% intervals do not overlap."""
    if "Ours" not in mcd:
        return "Ours was not measured."
    ours = mcd["Ours"]
    said = []
    for other in ("Lerp", "Slerp", "VRNN"):
        if other not in mcd:
            continue
        rates = [r for r in ours if r in mcd[other]]
        below = [
            r
            for r in rates
            if ours[r]["mean"] + ours[r]["ci95"] < mcd[other][r]["mean"] - mcd[other][r]["ci95"]
        ]
        above = [
            r
            for r in rates
            if ours[r]["mean"] - ours[r]["ci95"] > mcd[other][r]["mean"] + mcd[other][r]["ci95"]
        ]
        a, b = average(ours), average(mcd[other])
        verdict = "below" if a < b else "above"
        said.append(
            f"Ours averages {fmt(a)} against {other}'s {fmt(b)} ({verdict}); its interval lies "
            f"wholly below {other}'s at SR {', '.join(below) or 'none'} and wholly above at SR "
            f"{', '.join(above) or 'none'}"
        )
    return "; ".join(said) + "."


def interpolation(rows, stamp, out: Path, bodies: tuple[str, ...]) -> None:
    """table11_12_interpolation.{md,json}, table11_12_<body>.png and table11_12_keypoints.md."""
    sections, keypoint_sections = [], []
    for row in rows:
        body = row["body"]
        picture = f"table11_12_{body}.png"
        viz.plot_mcd(out / picture, row["interpolation"], title=f"{body}: M-CD x1e3")
        provenance.stamp_png(out / picture, stamp)
        sections += [
            f"Made by: {_made_by(row)}.",
            "",
            *interpolation_table(row["interpolation"], body),
            f"What it shows: {interpolation_ordering(row['interpolation'])}",
            "",
            f"![M-CD]({picture})",
            "",
        ]
        keypoint_sections += interpolation_table(row["interpolation_keypoints"], body)
    settings = rows[0]["settings"] if rows else {}
    head = (
        f"Every row: `experiments/paper_phase2.py` (phase 2 on the body's seed-0 `cpu`-preset "
        f"phase-1 row), then `nmjax.evaluate.evaluate_run` with {settings.get('trajectories')} "
        f"trajectories per generative method and up to {settings.get('max_segments')} keyframe "
        f"pairs per sequence and rate.\n\n{_missing(rows, bodies)}"
    )
    provenance.write_markdown(
        out / "table11_12_interpolation.md",
        "# Tables 11-12: interpolation M-CD x1e3 (Eq. 22; 95% CI over test sequences)\n\n"
        f"{head}\n" + "\n".join(sections) + f"\n{PAPER_MCD}\n",
        stamp,
    )
    provenance.write_json(
        out / "table11_12_interpolation.json",
        {r["body"]: {"interpolation": r["interpolation"], "made_by": _made_by(r)} for r in rows},
        stamp,
    )
    provenance.write_markdown(
        out / "table11_12_keypoints.md",
        "# Tables 11-12, decoder-free: in-between keypoint error of the interpolations\n\n"
        "Sum over K of the squared xyz error of the in-between keypoints against the observed "
        f"ones (mean over frames; 95% CI over test sequences).\n\n{head}\n"
        + "\n".join(keypoint_sections)
        + "\n",
        stamp,
    )


def _at(results: dict, method: str, n: str, measure: str) -> dict | None:
    entry = results["methods"].get(method, {}).get(n, {}).get(measure)
    return entry if entry and math.isfinite(entry.get("mean", math.nan)) else None


def generation_findings(results: dict) -> str:
    """A paragraph of the comparisons a generation evaluation supports, read off its numbers."""
    horizons = [str(n) for n in results["settings"]["horizons"]]
    methods = [m for m in ("Ours", "VRNN") if m in results["methods"]]
    longest = horizons[-1]
    said = []
    bones = {m: _at(results, m, longest, "bone_error") for m in methods}
    real_bones = results["real"][longest].get("bone_error")
    said.append(
        f"At N = {longest} the bone-length error is "
        + ", ".join(f"{fmt(b['mean'], b['ci95'])} for {m}" for m, b in bones.items() if b)
        + (
            f" (the real test clips: {fmt(real_bones['mean'], real_bones['ci95'])})"
            if real_bones
            else " (no real test clip is that long to compare with)"
        )
        + "; Ours places joints by forward kinematics, so its bones keep the lengths measured on"
        " the conditioning frames (up to float round-off, on bones of the pruned tree that skip"
        " no pruned joint)."
    )
    div = {m: [_at(results, m, n, "diversity") for n in horizons] for m in methods}
    said.append(
        "Diversity (APD of the samples of one clip) from N = "
        f"{horizons[0]} to {longest}: "
        + "; ".join(
            f"{m} " + " -> ".join(fmt(d["mean"]) if d else "n/a" for d in values)
            for m, values in div.items()
        )
        + " (hold-last-pose: 0)."
    )
    measured = [n for n in horizons if _at(results, "Hold last pose", n, "set_distance")]
    missing = [n for n in horizons if n not in measured]
    for n in measured:
        found = {
            m: _at(results, m, n, "set_distance")
            for m in (*methods, "Hold last pose")
            if _at(results, m, n, "set_distance")
        }
        best = min(found, key=lambda m: found[m]["mean"])
        lo, hi = (found[best]["mean"] + s * found[best]["ci95"] for s in (-1, 1))
        overlap = [
            m
            for m, r in found.items()
            if m != best and abs(r["mean"] - found[best]["mean"]) <= r["ci95"] + found[best]["ci95"]
        ]
        said.append(
            f"Set distance to real clips at N = {n}: "
            + ", ".join(f"{m} {fmt(r['mean'], r['ci95'])}" for m, r in found.items())
            + f"; {best} is closest ({fmt(lo)} to {fmt(hi)})"
            + (f", within the intervals of {', '.join(overlap)}." if overlap else ".")
        )
    if missing:
        said.append(
            f"At N = {', '.join(missing)} the set distance is n/a: "
            + results["methods"]["Ours"][missing[0]]["set_distance"]["reason"]
            + ", so only diversity and bone-length error are measured there."
        )
    return " ".join(said)


def generation(row, stamp, out: Path) -> None:
    """generation_<body>.{md,json,png}."""
    body, results = row["body"], row["generation"]
    picture = f"generation_{body}.png"
    viz.plot_generation(out / picture, results, reference=REFERENCE, title=f"{body}: generation")
    provenance.stamp_png(out / picture, stamp)
    st = results["settings"]
    text = [
        f"# Generation on {body}: diversity, bone-length error, set distance to real motion",
        "",
        f"Made by: {_made_by(row)}.",
        "",
        f"{len(results['clips'])} conditioning clips of {st['cond']} test frames ({st['clips']} "
        f"per test sequence, inputs {st.get('inputs')}), {st['samples']} samples each; horizon "
        f"N = frames generated after them; distances are mean per-frame keypoint distances "
        f"(normalised units) over the {st['kept_nodes']} nodes of the pruned skeleton; hold "
        "last pose repeats the last conditioning frame.",
        "",
        *generation_tables(results),
        f"![each measure against the horizon]({picture})",
        "",
        "## What it shows",
        "",
        generation_findings(results),
        "",
    ]
    provenance.write_markdown(out / f"generation_{body}.md", "\n".join(text), stamp)
    provenance.write_json(
        out / f"generation_{body}.json", {**results, "made_by": _made_by(row)}, stamp
    )


def training(row, stamp, out: Path) -> None:
    """train_dyn_<body>.{json,png}: both models' curves, final validation and speed."""
    body = row["body"]
    stem = out / f"train_dyn_{body}"
    curves = {MODELS[m]: info["curve"] for m, info in row["models"].items()}
    viz.plot_phase2_curves(
        stem.with_suffix(".png"), curves, f"phase 2 on {body}'s phase-1 row {row['phase1']['row']}"
    )
    provenance.stamp_png(stem.with_suffix(".png"), stamp)
    provenance.write_json(
        stem.with_suffix(".json"),
        {"body": body, "phase1": row["phase1"], "made_by": _made_by(row), **row["models"]},
        stamp,
    )


def render(rows: list[dict[str, Any]], out: Path, bodies: tuple[str, ...] = BODIES) -> None:
    """Every phase-2 file from `rows` into `out` (rows in body order)."""
    stamp = provenance.stamp()
    order = {b: i for i, b in enumerate(bodies)}
    rows = sorted((r for r in rows if r["body"] in order), key=lambda r: order[r["body"]])
    for row in rows:
        training(row, stamp, out)
        generation(row, stamp, out)
    interpolation(rows, stamp, out, bodies)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default = Path(__file__).parent / "results" / "phase2_rows.json"
    parser.add_argument("--rows", type=Path, default=default, help="the rows file")
    args = parser.parse_args(argv)
    render(json.loads(args.rows.read_text())["rows"], args.rows.parent)
    print(f"rendered the phase-2 tables into {args.rows.parent}")


if __name__ == "__main__":
    main()
