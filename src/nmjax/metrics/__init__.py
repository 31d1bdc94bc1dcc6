"""Evaluation metrics (docs/architecture.md §9), pure math: arrays in, arrays or floats out; nothing
here reads files or imports another part of nmjax.

- `sc`: SC-score (Eq. 21, Table 1).
- `skeleton_measures`: bone-length variation and the skeleton against the ground truth (joint
  distance, joint coverage, edge precision, bone recall, distinct nodes).
- `motion`: the measures of generated motion (diversity, set distance to real motion).
- `chamfer`: Chamfer distances, 4D tracking (Table 2) and M-CD (Eq. 22) on voxel grids.
- `rig_scores`: the field's scores of a rig: tree edit distance to the true tree, CD-J2J,
  CD-J2B, CD-B2B against the true skeleton, and the rig's fit error to its capture.

Every public name is importable from `nmjax.metrics` itself: `metrics.semantic_consistency(...)`.
"""

from nmjax.metrics.chamfer import (
    MAX_SQ_DIST,
    TRACKING_SCALE,
    chamfer_distance,
    motion_chamfer,
    point_chamfer,
    tracking_chamfer,
    voxel_points,
)
from nmjax.metrics.motion import (
    clip_distances,
    diversity,
    keypoint_distance,
    nearest_clip_distances,
    root_relative,
    set_distance,
    set_diversity,
)
from nmjax.metrics.rig_scores import (
    BONE_SAMPLES,
    SKELETON_CD_SCALE,
    cd_b2b,
    cd_j2b,
    cd_j2j,
    rig_fit_error,
    skeleton_chamfers,
    tree_edit_distance,
    unit_box,
)
from nmjax.metrics.sc import (
    SC_NODES,
    SemanticConsistency,
    nearest_keypoint_counts,
    sc_score_from_counts,
    semantic_consistency,
    skeleton_nodes,
)
from nmjax.metrics.skeleton_measures import (
    COVERAGE_RADII,
    TWO_HOPS,
    bone_length_variation,
    bone_lengths,
    bone_recall,
    distinct_nodes,
    edge_precision,
    joint_coverage,
    joint_distance,
    joint_nodes,
    joint_to_node_distances,
    nearest_kept_distance,
    node_joints,
    skeleton_agreement,
    tree_within,
)

__all__ = [
    "BONE_SAMPLES",
    "COVERAGE_RADII",
    "MAX_SQ_DIST",
    "SC_NODES",
    "SKELETON_CD_SCALE",
    "TRACKING_SCALE",
    "TWO_HOPS",
    "SemanticConsistency",
    "bone_length_variation",
    "bone_lengths",
    "bone_recall",
    "cd_b2b",
    "cd_j2b",
    "cd_j2j",
    "chamfer_distance",
    "clip_distances",
    "distinct_nodes",
    "diversity",
    "edge_precision",
    "joint_coverage",
    "joint_distance",
    "joint_nodes",
    "joint_to_node_distances",
    "keypoint_distance",
    "motion_chamfer",
    "nearest_clip_distances",
    "nearest_kept_distance",
    "nearest_keypoint_counts",
    "node_joints",
    "point_chamfer",
    "rig_fit_error",
    "root_relative",
    "sc_score_from_counts",
    "semantic_consistency",
    "set_distance",
    "set_diversity",
    "skeleton_agreement",
    "skeleton_chamfers",
    "skeleton_nodes",
    "tracking_chamfer",
    "tree_edit_distance",
    "tree_within",
    "unit_box",
    "voxel_points",
]
