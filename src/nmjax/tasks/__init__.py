"""What the learned model is for (paper Sec. 5, appendix A.4 and D.4; docs/architecture.md §9).

- `generate`: motion generation, `generate_motion`; `nmjax generate` (`run_generate`).
- `interpolate`: motion interpolation between keyframes, `interpolate_motion`, and the baselines
  Lerp and Slerp; `nmjax interpolate` (`run_interpolate`); `Interpolators` runs every method.
- `retarget`: motion retargeting (Eqs. 24-25) onto a target mesh, `retarget_mesh`;
  `nmjax retarget` (`run_retarget`).
- `inputs`: the clips the commands run on (test sequences as the phase-2 run was fed, or a
  point-sequence file).
- `outputs`: the files the commands write, each format's name, writer and reader (the rig arrays
  written beside every motion included), and `folder_kind`, what a run or output folder is.

The array functions are pure and jit-able; sampling is vmapped over trajectories; the
`*_jit` entry points take a model split once (`nnx.split`, graphdef static). The mesh and
point-file readers are `nmjax.data.meshes`. Every public name is importable from `nmjax.tasks`.
"""

from nmjax.tasks.generate import generate_jit, generate_motion, generation_clips, run_generate
from nmjax.tasks.inputs import TaskClips, pick_inputs, point_file_keypoints, source_file_clip
from nmjax.tasks.interpolate import (
    Interpolators,
    interpolate_jit,
    interpolate_motion,
    interpolation_clips,
    interpolation_weights,
    lerp_keypoints,
    run_interpolate,
    slerp_jit,
    slerp_keypoints,
)
from nmjax.tasks.outputs import (
    GENERATE_FILE,
    INTERPOLATE_FILE,
    INTERPOLATION_METHODS,
    RETARGET_FILE,
    RETARGET_FRAME,
    folder_kind,
    interpolated_methods,
    interpolation_methods,
    read_generate,
    read_interpolate,
    read_retarget,
    read_retarget_arrays,
    rig_arrays,
    rig_format,
    write_generate,
    write_interpolate,
    write_obj,
    write_retarget,
)
from nmjax.tasks.retarget import (
    detect_target_joints,
    infer_rotations,
    infer_rotations_jit,
    rest_rotations,
    retarget_joints,
    retarget_mesh,
    retarget_pose,
    retarget_vertices,
    run_retarget,
)

__all__ = [
    "GENERATE_FILE",
    "INTERPOLATE_FILE",
    "INTERPOLATION_METHODS",
    "RETARGET_FILE",
    "RETARGET_FRAME",
    "Interpolators",
    "TaskClips",
    "detect_target_joints",
    "folder_kind",
    "generate_jit",
    "generate_motion",
    "generation_clips",
    "infer_rotations",
    "infer_rotations_jit",
    "interpolate_jit",
    "interpolate_motion",
    "interpolated_methods",
    "interpolation_clips",
    "interpolation_methods",
    "interpolation_weights",
    "lerp_keypoints",
    "pick_inputs",
    "point_file_keypoints",
    "read_generate",
    "read_interpolate",
    "read_retarget",
    "read_retarget_arrays",
    "rest_rotations",
    "retarget_joints",
    "retarget_mesh",
    "retarget_pose",
    "retarget_vertices",
    "rig_arrays",
    "rig_format",
    "run_generate",
    "run_interpolate",
    "run_retarget",
    "slerp_jit",
    "slerp_keypoints",
    "source_file_clip",
    "write_generate",
    "write_interpolate",
    "write_obj",
    "write_retarget",
]
