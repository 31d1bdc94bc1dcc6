"""`nmjax evaluate --run RUN`: the paper's quantitative tables on the test split.

    nmjax evaluate --run runs/dyn-synth-hand-nm-... [--vrnn-run runs/dyn-...-vrnn-...] [--out DIR]
    nmjax evaluate --run runs/skel-synth-hand-...      (phase-1 metrics only)

- SC-score (Eq. 21, Table 1) and its standard deviation over ground-truth joints, on test crops
  of T frames (each crop normalised on its own, as in training), in the published definition
  ("sc": in each frame keypoints with alpha < 0.2 are no candidates) and with the fixed node set
  of the pruned skeleton ("sc_fixed_nodes").
- Bone-length variation of the pruned skeleton over the same crops (std / mean length per bone).
- The skeleton against the ground truth, on data with joints (docs/architecture.md §9; the kept
nodes and
  pruned tree stored in the run's skeleton.json, the true tree from the dataset's meta.json):
  joint distance (mean and 95% CI over test sequences), joint coverage at radius 0.05 and 0.10,
  edge precision (and within two hops), bone recall and distinct nodes (`metrics`).
- 4D-tracking Chamfer x1e4 (Table 2): reconstruction of every crop thresholded at 0.5 against its
  voxels, averaged per sequence; mean and 95% confidence interval over test sequences.
- The field's scores, beside SC (`metrics.rig_scores`): the tree edit distance of the kept tree
  to the true tree (APTED, unit insert and delete, rename free); CD-J2J, CD-J2B and CD-B2B x1e-2
  of the kept nodes against the true joints in each frame's body box scaled to [-0.5, 0.5]^3;
  the fit error of the rig `nmjax export` builds (each crop's frame-0 points skinned with
  Algorithm 2's weights and driven by the rig, against every frame's points), Chamfer x1e4 in
  the cube and in the capture's units.
- Interpolation M-CD (Eq. 22, Tables 11-12) at sampling rates SR = 3, 5, ..., 30 for Ours (the
  "nm" dynamics), VRNN (a positional "vrnn" run on the same phase-1 run, when one is given or
  found next to RUN), Lerp and Slerp. Keyframes x_ts, x_te = x_{ts+SR} are taken every SR frames
  of each test sequence, as the phase-2 run was fed (its `inputs`): "crop", each clip ts..te (at
  least T frames) normalised with its own bounding box and run through the detector;
  "sequence", cut from the whole sequence normalised with one box (keypoints_test.npz). Each
  method's keypoints are turned into voxels by the phase-1 decoder (gaussian maps of the
  keypoints + the features of frame ts, Eq. 7) thresholded at 0.5 and compared with the true
  voxels of the same clip on difference voxels. Reported x1e3 (the paper does not state its
  scale); mean and 95% confidence interval over test sequences.

Writes `<out>/results.json`, `<out>/tables.md` and `<out>/mcd.png` (default out: `<run>/eval`),
each stamped with the commit, machine and metric definitions (`nmjax.provenance`).

    nmjax evaluate --run RUN [--vrnn-run RUN2] --generation [--horizons 25,100,300] [--samples 10]

evaluates generation instead (beyond the paper, which shows it only as pictures): on conditioning
clips of T_cond test frames (on "crop" inputs detected as the release's generation does, the
first T_cond frames of the clip's first crop normalised on its own), S futures per clip from Ours,
VRNN and the hold-last-pose baseline,
at each horizon N (generated frames) the diversity (average pairwise distance of the S samples,
and of the generated set as a whole), the bone-length error of the generated frames
(`metrics.bone_length_variation` on the pruned skeleton) and the set distance to the real test
clips of N frames (`metrics.set_distance`), with 95% confidence intervals over clips. Writes
`<out>/generation.json`, `generation.md` and `generation.png` (each measure against N).

The package, by job: `phase1` (SC-score, tracking, the skeleton measures), `field_scores` (the
tree edit distance, CD-J2J / J2B / B2B and the rig's fit error of a phase-1 run), `phase2`
(interpolation M-CD and `evaluate_run`, the command), `generation` (the generation measures and
their command), `tables` (the markdown of results.json), `stats` (means and confidence
intervals). Every public name is importable from `nmjax.evaluate`.
"""

from nmjax.evaluate.field_scores import (
    FIT_KEYS,
    FIT_POINTS,
    SKELETON_CD_KEYS,
    crop_fit_error,
    crop_rig,
    field_scores,
    fit_subset,
    sequence_scores,
    skinned_surface,
)
from nmjax.evaluate.generation import (
    GEN_HORIZONS,
    GEN_MEASURES,
    GEN_METHODS,
    GENERATION_METRICS,
    INPUTS_NOTE,
    REFERENCE,
    conditioning_clips,
    crop_conditioning,
    evaluate_generation,
    evaluate_generation_run,
    generated_futures,
    generation_markdown,
    generation_measures,
    generation_tables,
    hold_last_pose,
    real_clips,
    real_reference,
)
from nmjax.evaluate.phase1 import (
    PHASE1_METRICS,
    evaluate_phase1,
    normalized_crops,
    phase1_crops,
    phase1_outputs,
    phase1_scores,
    picture_frame,
    skeleton_against_truth,
    true_tree,
)
from nmjax.evaluate.phase2 import (
    INTERPOLATION_METRICS,
    MCD_SCALE,
    METHODS,
    SAMPLING_RATES,
    evaluate_interpolation,
    evaluate_run,
    keyframe_clips,
    keyframe_starts,
)
from nmjax.evaluate.stats import confidence_interval, summarize, summarize_per_rate
from nmjax.evaluate.tables import (
    RIG_SCORES_COLUMNS,
    RIG_SCORES_NOTE,
    SKELETON_TRUTH_COLUMNS,
    SKELETON_TRUTH_NOTE,
    fmt,
    interpolation_table,
    markdown_tables,
    rig_scores_table,
    skeleton_truth_table,
)

__all__ = [
    "FIT_KEYS",
    "FIT_POINTS",
    "GENERATION_METRICS",
    "GEN_HORIZONS",
    "GEN_MEASURES",
    "GEN_METHODS",
    "INPUTS_NOTE",
    "INTERPOLATION_METRICS",
    "MCD_SCALE",
    "METHODS",
    "PHASE1_METRICS",
    "REFERENCE",
    "RIG_SCORES_COLUMNS",
    "RIG_SCORES_NOTE",
    "SAMPLING_RATES",
    "SKELETON_CD_KEYS",
    "SKELETON_TRUTH_COLUMNS",
    "SKELETON_TRUTH_NOTE",
    "conditioning_clips",
    "confidence_interval",
    "crop_conditioning",
    "crop_fit_error",
    "crop_rig",
    "evaluate_generation",
    "evaluate_generation_run",
    "evaluate_interpolation",
    "evaluate_phase1",
    "evaluate_run",
    "field_scores",
    "fit_subset",
    "fmt",
    "generated_futures",
    "generation_markdown",
    "generation_measures",
    "generation_tables",
    "hold_last_pose",
    "interpolation_table",
    "keyframe_clips",
    "keyframe_starts",
    "markdown_tables",
    "normalized_crops",
    "phase1_crops",
    "phase1_outputs",
    "phase1_scores",
    "picture_frame",
    "real_clips",
    "real_reference",
    "rig_scores_table",
    "sequence_scores",
    "skeleton_against_truth",
    "skeleton_truth_table",
    "skinned_surface",
    "summarize",
    "summarize_per_rate",
    "true_tree",
]
