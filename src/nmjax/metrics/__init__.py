"""Evaluation metrics (DESIGN §9), pure math: arrays in, arrays or floats out; nothing here reads
files or imports another part of nmjax.

- `sc`: SC-score (Eq. 21, Table 1).
- `skeleton_measures`: bone-length variation and the skeleton against the ground truth (joint
  distance, joint coverage, edge precision, bone recall, distinct nodes).
- `motion`: the measures of generated motion (diversity, set distance to real motion).
- `chamfer`: Chamfer distances, 4D tracking (Table 2) and M-CD (Eq. 22) on voxel grids.

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
    "COVERAGE_RADII",
    "MAX_SQ_DIST",
    "SC_NODES",
    "TRACKING_SCALE",
    "TWO_HOPS",
    "SemanticConsistency",
    "bone_length_variation",
    "bone_lengths",
    "bone_recall",
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
    "root_relative",
    "sc_score_from_counts",
    "semantic_consistency",
    "set_distance",
    "set_diversity",
    "skeleton_agreement",
    "skeleton_nodes",
    "tracking_chamfer",
    "tree_within",
    "voxel_points",
]
