"""The evaluation's markdown: Table 1 (SC-score), the skeleton against the ground truth, the
field's scores (tree edit distance, CD-J2J / J2B / B2B, the rig's fit error), Table 2 (4D
tracking) and Tables 11-12 (interpolation M-CD) layouts, and the number format they share.
"""

from __future__ import annotations

import numpy as np

from nmjax import metrics


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


# The field's scores (`nmjax.evaluate.field_scores`): (results key, column title).
RIG_SCORES_COLUMNS = (
    ("tree_edit_distance", "TED"),
    ("cd_j2j", "CD-J2J x1e-2"),
    ("cd_j2b", "CD-J2B x1e-2"),
    ("cd_b2b", "CD-B2B x1e-2"),
    ("rig_fit_cd", "rig fit CD x1e4"),
    ("rig_fit_cd_capture", "rig fit CD, capture units^2"),
)
RIG_SCORES_NOTE = (
    "TED = tree edit distance between the kept tree and the true tree (rooted, unlabelled; "
    "APTED, insert 1, delete 1, rename 0). CD-J2J / J2B / B2B = RigNet's joint-to-joint, "
    "joint-to-bone and bone-to-bone Chamfer distances, symmetric means of nearest Euclidean "
    "distances between the kept nodes and the true joints, each frame's body box scaled to "
    "[-0.5, 0.5]^3, x1e-2. Rig fit CD = each test crop's frame-0 points skinned (Algorithm 2's "
    "weights, linear blend skinning) by the rig `nmjax export` builds, against the points of "
    "every frame: Chamfer of squared distances, x1e4 in the cube (Table 2's units) and in the "
    "capture's units. 95% CI over test sequences in parentheses; n/a: the data lacks joints or "
    "the true tree, or the run lacks a skeleton."
)


def rig_scores_table(rows: dict[str, dict]) -> list[str]:
    """Markdown lines of the field's scores (`RIG_SCORES_COLUMNS`), one row per {label: phase-1
    results of `evaluate_phase1`}; "n/a" where a row lacks a score; no lines when no row has
    any."""
    if not any(key in p1 for p1 in rows.values() for key, _ in RIG_SCORES_COLUMNS):
        return []
    titles = [t for _, t in RIG_SCORES_COLUMNS]
    lines = ["| model | " + " | ".join(titles) + " |", "|---|" + "---|" * len(titles)]
    for label, p1 in rows.items():
        cells = []
        for key, _ in RIG_SCORES_COLUMNS:
            value = p1.get(key)
            if value is None:
                cells.append("n/a")
            elif key == "tree_edit_distance":
                cells.append(str(value))
            else:
                cells.append(fmt(value["mean"], value["ci95"]))
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
    table = rig_scores_table({"Ours": p1})
    if table:
        lines += ["## The field's scores: tree, skeleton and rig fit", "", RIG_SCORES_NOTE, ""]
        lines += [*table, ""]
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
