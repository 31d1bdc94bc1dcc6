"""`nmjax view`: a run folder as a 3D scene in the browser, frame by frame (viser).

Four kinds of input, told apart by what they hold:

- a phase-1 run (`nmjax train-skel`): one sequence of a split with its points (or occupied
  voxels), the detector's keypoints of every frame (colour by index, size by intensity alpha,
  the nodes the skeleton prunes in grey), the bones of the pruned skeleton between kept nodes
  with the root marked, the ground-truth joints and tree where the dataset has them, the refined
  skeleton of a sequence `nmjax refine` refined, and the learned affinity (the influence max_n
  A_n of docs/architecture.md §7) as the opacity of a line between every pair of keypoints;
- a phase-2 run (`nmjax train-dyn`, model "nm"): the sequence's conditioning frames and S
  generated continuations side by side, and below them the interpolation of a gap by the model
  beside the Lerp and Slerp baselines (and the positional VRNN when a run of it lies beside);
- a retarget output folder (`nmjax retarget`): the posed target mesh of every frame with its
  retargeted joints, beside the source motion;
- a glTF file written by `nmjax export` (.glb / .gltf): its skeleton and skinned mesh posed at
  every key of its animation by glTF's own rules (`nmjax.export.gltf.read`), so a file can be
  checked before it is sent on.

Everything drawn comes from the run-folder readers (`nmjax.train.trained`) and the task functions
(`nmjax.tasks`); nothing here runs a model of its own. viser is imported only when a viewer
starts (`pip install -e '.[view]'`), so the rest of nmjax never needs it.

The package, by job: `draw` (plain functions of arrays: colours, sizes, pairs, axes), `viewer`
(the base viewer, its controls and recording, and `Pose`), one module per kind of input
(`phase1`, `phase2` with retarget outputs, `exported` for glTF files) and `server` (starting a
view). Every public name is importable from `nmjax.view`.
"""

from nmjax.view.draw import (
    AFFINITY_COLOR,
    BODY_COLOR,
    BONE_COLOR,
    GENERATED_BONE_COLOR,
    GREY,
    KEYPOINT_RADIUS,
    MESH_COLOR,
    MIN_SIZE,
    PANEL_SPACING,
    POINT_SIZE,
    REFINED_COLOR,
    ROOT_COLOR,
    TRUTH_COLOR,
    affinity_pairs,
    bone_pairs,
    clamp_frame,
    cylinder_transforms,
    keypoint_colors,
    keypoint_radii,
    unit_cylinder,
    view_axes,
)
from nmjax.view.exported import GltfViewer
from nmjax.view.phase1 import Phase1Data, Phase1Viewer, read_phase1
from nmjax.view.phase2 import Phase2Data, Phase2Viewer, RetargetViewer, read_phase2
from nmjax.view.server import (
    EXTRA,
    GLTF_SUFFIXES,
    UP_AXES,
    check_port,
    folder_kind,
    import_viser,
    open_view,
    pick_sequence,
    start_server,
)
from nmjax.view.viewer import Pose, Viewer

__all__ = [
    "AFFINITY_COLOR",
    "BODY_COLOR",
    "BONE_COLOR",
    "EXTRA",
    "GENERATED_BONE_COLOR",
    "GLTF_SUFFIXES",
    "GREY",
    "KEYPOINT_RADIUS",
    "MESH_COLOR",
    "MIN_SIZE",
    "PANEL_SPACING",
    "POINT_SIZE",
    "REFINED_COLOR",
    "ROOT_COLOR",
    "TRUTH_COLOR",
    "UP_AXES",
    "GltfViewer",
    "Phase1Data",
    "Phase1Viewer",
    "Phase2Data",
    "Phase2Viewer",
    "Pose",
    "RetargetViewer",
    "Viewer",
    "affinity_pairs",
    "bone_pairs",
    "check_port",
    "clamp_frame",
    "cylinder_transforms",
    "folder_kind",
    "import_viser",
    "keypoint_colors",
    "keypoint_radii",
    "open_view",
    "pick_sequence",
    "read_phase1",
    "read_phase2",
    "start_server",
    "unit_cylinder",
    "view_axes",
]
