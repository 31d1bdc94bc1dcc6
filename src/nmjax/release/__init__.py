"""The authors' released model as two nmjax run folders (`nmjax import-release`), without PyTorch.

The authors' repository ships one trained network, `pretrained/aist/aist_pretrained.pth`, with
the options of its run, `pretrained/aist/opt.pickle`. This package turns the pair into a phase-1
and a phase-2 run folder that every nmjax command reads (`runs`), as if `train-skel` and
`train-dyn` had written them. One module per job:

- `checkpoint`: `read_checkpoint`, PyTorch's zip checkpoint read into NumPy arrays by a
  restricted unpickler (reading can never run code); `read_options`, opt.pickle admitting only
  `argparse.Namespace`.
- `options`: `configs_from_options`, the two run configurations from the options (grid, K, D_z,
  D_h, T, sample rate, loss weights) and the widths the tensors fix.
- `layout`: the name/layout map, `detector_entries` and `dynamics_entries`, from the release's
  tensor names (shared/release/aist_state_dict.tsv) onto the parameters of `KeypointDetector`
  and `Dynamics`, each with its layout conversion; `network_widths`, `expected_tensors`.
- `convert`: `fill` applies the map and refuses a tensor left over, a parameter left unfilled,
  or shapes that disagree, naming them; `build_networks` builds and fills both networks.
- `run_writing`: config.json and checkpoint 0 of each imported run (its phase-1 artefacts go
  through `nmjax.run_folder.write_phase1_artifacts`, as a trained run's do).
- `importer`: `import_release`, all of it, written atomically (a temporary folder renamed onto
  DIR).

Only NumPy is imported here: JAX, Flax and the rest of nmjax load when a function needs them.
"""

from nmjax.release.checkpoint import Checkpoint, read_checkpoint, read_options
from nmjax.release.convert import build_networks, check_all_used, fill
from nmjax.release.importer import (
    PROVENANCE_FILE,
    check_run_folder,
    import_record,
    import_release,
    keypoint_motion,
)
from nmjax.release.layout import (
    CONV,
    CONV_TRANSPOSE,
    LINEAR,
    POINTWISE,
    Entry,
    Layout,
    Widths,
    conv_kernel,
    conv_transpose_kernel,
    detector_entries,
    dynamics_entries,
    expected_tensors,
    linear_kernel,
    network_widths,
    offset_directions,
    pointwise_kernel,
)
from nmjax.release.options import SUPPORTED_OPTIONS, configs_from_options

__all__ = [
    "CONV",
    "CONV_TRANSPOSE",
    "LINEAR",
    "POINTWISE",
    "PROVENANCE_FILE",
    "SUPPORTED_OPTIONS",
    "Checkpoint",
    "Entry",
    "Layout",
    "Widths",
    "build_networks",
    "check_all_used",
    "check_run_folder",
    "configs_from_options",
    "conv_kernel",
    "conv_transpose_kernel",
    "detector_entries",
    "dynamics_entries",
    "expected_tensors",
    "fill",
    "import_record",
    "import_release",
    "keypoint_motion",
    "linear_kernel",
    "network_widths",
    "offset_directions",
    "pointwise_kernel",
    "read_checkpoint",
    "read_options",
]
