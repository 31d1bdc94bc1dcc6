"""Configuration: frozen dataclasses, the per-dataset values of paper Tables 3-8 and the presets.

A run is described by one `SkelTrainConfig` (phase 1) or `DynTrainConfig` (phase 2), each with the
same groups: `data` (a `DatasetConfig`: `data.name`, `data.root`, `data.frames`,
`data.batch_size` mean the same in both phases; each phase adds its own fields, `DataConfig`,
`DynDataConfig`), `model`, `optim`, `loop`. A preset is a named table of values (`PRESETS`) set
over a dataset's own configuration by `skel_preset(data, preset)` / `dyn_preset(data, preset)`;
every field can be overridden from the command line with `--set FIELD=VALUE` (`nmjax.config_io`,
which also reads and writes config.json, the older layouts included).
`preset="default"` is the paper's configuration (G=64, C=128); `preset="cpu"` shrinks grid and
channels so that training runs on a laptop-class CPU; `preset="tiny"` is for tests.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, ClassVar

from nmjax.config_io import replace_fields, replace_paths


@dataclass(frozen=True)
class DatasetSpec:
    """Per-dataset values of paper Tables 4-8 (the released code's per-dataset settings)."""

    name: str
    sample_rate: int  # take every n-th frame of the original sequence
    num_keypoints: int  # K
    sigma_g: float  # gaussian-map width, in cells of the heatmap grid
    decay_epochs: tuple[int, int]  # epochs at which the learning rate becomes 0.25x, then 0.1x
    w_vol: float
    w_traj: float
    w_local: float
    epochs: int = 200  # phase-1 length in the release's train.py (AIST++ 200, D-FAUST 2,000)
    synthetic: bool = False
    # Frames per second of the source sequences (before `sample_rate`): AIST++ and D-FAUST are
    # recorded at 60; the others state no rate, so 30 is assumed (`nmjax export --fps` overrides).
    fps: float = 30.0
    # > 0: phase 1 trains this many steps instead of `epochs` (the decays at the fractions of the
    # run that `decay_epochs` are of `epochs`), with one Adam state: for a set of one or a few
    # sequences, whose epoch (ceil(sequences / batch) steps) is a single step.
    steps: int = 0


DATASETS: dict[str, DatasetSpec] = {
    spec.name: spec
    for spec in (
        DatasetSpec("aist", 2, 24, 1.5, (60, 140), w_vol=10.0, w_traj=1.0, w_local=1e-3, fps=60.0),
        DatasetSpec(
            "dfaust",
            5,
            24,
            1.5,
            (600, 1400),
            w_vol=10.0,
            w_traj=1.0,
            w_local=1e-3,
            epochs=2000,
            fps=60.0,
        ),
        DatasetSpec("hanco", 1, 28, 1.0, (120, 170), w_vol=0.1, w_traj=1e-6, w_local=1.0),
        DatasetSpec("panda", 1, 12, 1.5, (60, 140), w_vol=10.0, w_traj=1e-3, w_local=1.0),
        DatasetSpec("animals", 1, 24, 2.0, (120, 170), w_vol=10.0, w_traj=1e-6, w_local=1e-3),
        # DeformingThings4D's humanoids are in no table of the paper: its animals' settings.
        DatasetSpec(
            "dt4d-humanoids", 1, 24, 2.0, (120, 170), w_vol=10.0, w_traj=1e-6, w_local=1e-3
        ),
        # Built-in synthetic bodies borrow the settings of their real counterpart.
        DatasetSpec(
            "synth-hand",
            1,
            28,
            1.0,
            (120, 170),
            w_vol=0.1,
            w_traj=1e-6,
            w_local=1.0,
            synthetic=True,
        ),
        DatasetSpec(
            "synth-arm",
            1,
            12,
            1.5,
            (60, 140),
            w_vol=10.0,
            w_traj=1e-3,
            w_local=1.0,
            synthetic=True,
        ),
        DatasetSpec(
            "synth-human",
            1,
            24,
            1.5,
            (60, 140),
            w_vol=10.0,
            w_traj=1.0,
            w_local=1e-3,
            synthetic=True,
        ),
        DatasetSpec(
            "synth-quadruped",
            1,
            24,
            2.0,
            (120, 170),
            w_vol=10.0,
            w_traj=1e-6,
            w_local=1e-3,
            synthetic=True,
        ),
        # A user's own capture (`nmjax prepare-data --from RAW` without --data), of a body nobody
        # tuned for: Table 3's weights, which every dataset starts from (w_vol 10, w_traj 1.0,
        # w_local 1e-3; the per-dataset changes of Tables 4-8 were made for a hand, an arm, an
        # animal), K = 24 (pruning keeps what the body needs) and sigma_g 1.5. A capture is one
        # or a few sequences, so the release's 200 epochs would be 200 steps: it trains 20,000
        # steps instead (the horizon of experiments/phase1_budget.py; a round count, not a
        # measured optimum), decays at 30% and 70% (the release's 60 and 140 of 200 epochs), Adam
        # at 4e-4 never restarted (an epoch is one step). Frame rate and up axis come from the
        # set's meta.json (`nmjax.data.layout.capture_meta`); 30 fps is the fallback.
        DatasetSpec(
            "capture", 1, 24, 1.5, (60, 140), w_vol=10.0, w_traj=1.0, w_local=1e-3, steps=20_000
        ),
    )
}


def dataset_spec(name: str) -> DatasetSpec:
    """Returns the spec of dataset `name`; unknown names list the valid ones."""
    if name not in DATASETS:
        raise ValueError(f"unknown dataset {name!r}; valid names: {', '.join(sorted(DATASETS))}")
    return DATASETS[name]


def frame_rate(name: str, sample_rate: int, fps: float = 0.0) -> float:
    """Frames per second of a run's keypoint sequences: every `sample_rate`-th frame of dataset
    `name`, recorded at `fps` (`DataConfig.fps`; 0: the dataset's `DatasetSpec.fps`)."""
    return (fps if fps > 0 else dataset_spec(name).fps) / sample_rate


@dataclass(frozen=True)
class DatasetConfig:
    """What both phases' `data` group says alike: which dataset, where it lives, and the crops a
    step trains on (`cfg.data.name`, `root`, `frames`, `batch_size` mean the same in phase 1 and
    phase 2).

    Each phase extends it with what only it reads (`DataConfig`, `DynDataConfig`): phase 1
    voxelises the sequences itself, so grid, sample rate, loader and augmentation are its own;
    phase 2 reads them through the phase-1 run's detector, and adds only how its keypoint crops
    are made.
    """

    name: str = "synth-hand"
    # The dataset's folder. Phase 1: default data/<name>. Phase 2: default the phase-1 run's
    # (`data.root` of its config), where the "crop" inputs read the sequences from.
    root: str | None = None
    frames: int = 10  # T of one training crop
    batch_size: int = 3  # B, the global batch


@dataclass(frozen=True)
class DataConfig(DatasetConfig):
    """Phase 1's data: which sequences are read and how they are cropped, normalised and
    voxelised."""

    grid: int = 64  # G
    sample_rate: int = 1
    seed: int = 0
    worker_count: int = 0  # grain worker processes; 0 = load in the main process
    prefetch: int = 2  # batches prepared ahead of the device
    # Training-crop augmentation (off in the paper's recipe; experiments/phase1_study.py measures
    # it): each crop rotated about the up axis by an angle uniform in +-rotate_degrees before
    # normalisation, then shrunk by a factor uniform in [1 - scale_jitter, 1] towards the
    # normalised box's minimum corner, so it stays inside the grid. Validation and test crops
    # are never augmented.
    rotate_degrees: float = 0.0
    scale_jitter: float = 0.0
    up_axis: int = 2  # 0/1/2 = x/y/z; the synthetic bodies have z up
    # Frames per second of the set's sequences; 0: the dataset's (`DatasetSpec.fps`). A capture
    # records its own in meta.json, which `nmjax train-skel` copies here with its up axis.
    fps: float = 0.0


@dataclass(frozen=True)
class DynDataConfig(DatasetConfig):
    """Phase 2's data: the keypoint crops of the phase-1 run that the model trains on.

    The grid, sample rate and normalisation are the phase-1 run's (its detector's `DataConfig`).
    """

    frames: int = 20  # T_dyna
    batch_size: int = 16
    # What the model is fed (DYN_INPUTS). "crop", the release's: every T-frame crop normalised
    # with its own bounding box and run through the frozen phase-1 detector, so the keypoints (and
    # the detector's temporal mean behind them) are those of that crop; generation and
    # interpolation condition on clips detected the same way. "sequence": crops cut from the
    # whole-sequence keypoints_*.npz (each sequence normalised with one box, detected in
    # consecutive windows), which needs no detector in phase 2: the named fast route.
    inputs: str = "crop"


@dataclass(frozen=True)
class LossWeights:
    """Weights of Eq. 23 (Table 3 plus the per-dataset Tables 4-8)."""

    recon: float = 100.0
    sparse: float = 5.0
    sep: float = 0.1
    vol: float = 10.0
    local: float = 1e-3
    time: float = 1.0
    complex: float = 0.01
    traj: float = 1.0
    sep_sigma: float = 0.02  # sigma_s = 1 / (2 sigma^2) = 1250
    intensity_weighted: bool = False  # True: Eqs. 13, 15, 16 as printed
    # "volume": Eq. 8. "joints": the ground-truth-supervised baseline of Table 2, L_vol replaced
    # by the MSE between keypoint k and ground-truth joint k (needs K = J and joints in the data).
    vol_target: str = "volume"


@dataclass(frozen=True)
class DetectorConfig:
    """Keypoint detector of paper Fig. 8-9 (docs/architecture.md §6)."""

    grid: int = 64  # G; heatmaps live on g = G / heatmap_stride
    # 4: the paper (16^3 heatmaps at G=64). 2: one pooling level less before the hourglass and
    # one upsampling less in the decoder (16^3 heatmaps at G=32: slower, and on synth-arm at the
    # cpu preset no better; experiments/results/NOTES.md).
    heatmap_stride: int = 4
    num_keypoints: int = 24  # K
    channels: int = 128  # C
    hourglass_channels: tuple[int, int, int] = (32, 48, 72)
    sigma_g: float = 1.5
    num_affinity: int = 2  # N
    decoder_sharpness: float = 10.0
    # Keypoint positions mu from heatmap^(1 / keypoint_temperature) (`keypoints.
    # heatmap_to_keypoints`); 1 is the paper's expectation under the fused heatmap itself.
    keypoint_temperature: float = 1.0
    # Precision of the 3D convolutions ("float32" | "bfloat16": inputs and kernels cast, results
    # back to float32); parameters, GroupNorm, heatmaps, keypoints and losses stay float32.
    compute_dtype: str = "float32"
    # How the 3D convolutions are evaluated (`models.conv_kernels.resolve`): "auto" takes XLA's
    # native convolution on GPU/TPU and the CPU forms on CPU; "native", "per_tap", "stacked" or
    # "winograd" that form on every backend. Every form computes the same function; Winograd's
    # rounds differently from the direct sums (`conv_kernels.winograd_conv3d_valid`).
    conv_form: str = "auto"
    # Initial weights. "release": the released network's (`models.blocks.INIT_STD`,
    # `FEATURE_INIT_STD`). "fan_in": nmjax's earlier choice, every convolution kernel N(0,
    # 1 / fan_in) (LeCun normal) and the heatmap fusion starting at 1 x frame heatmap - 4, which
    # spreads an untrained detector's keypoints over the body instead of one spot.
    init: str = "release"


@dataclass(frozen=True)
class OptimConfig:
    """The optimiser both phases train with (`nmjax.train.optim`): Adam with a piecewise-constant
    learning rate, optional clipping, Adam's restarts and an optional weight average.

    The release's recipe (docs/architecture.md §6b) is Adam at 4e-4 for every dataset and phase,
    created anew every epoch, no clipping, the rate 0.25x then 0.1x of the initial from each decay
    epoch (phase 1; phase 2 does not decay).
    """

    learning_rate: float = 4e-4
    # Epochs at which the rate becomes lr_decay[0]x, then lr_decay[1]x the initial one; turned
    # into `lr_milestones` (steps) when the epochs are resolved (`resolve_epochs`).
    decay_epochs: tuple[int, ...] = ()
    lr_milestones: tuple[int, ...] = ()  # steps; scaled by lr_decay
    lr_decay: tuple[float, ...] = (0.25, 0.1)
    clip_norm: float = 0.0  # global-norm clipping of every step; 0: none (the release's)
    # "epoch": Adam's state (moments and bias correction) restarts at every epoch boundary, as
    # the release creates its optimizer anew each epoch; "never": one state for the whole run.
    optimizer_reset: str = "epoch"
    # > 0: also keep an exponential moving average of the weights with this decay per step
    # (bias-corrected), and validate, checkpoint-select and export the averaged model; 0 (the
    # paper): the weights as trained.
    ema_decay: float = 0.0


@dataclass(frozen=True)
class LoopConfig:
    """How long a run trains and what the one training loop (`nmjax.train.loop`) reports.

    The run's length is counted as the release counts it (docs/architecture.md §6b). epochs > 0:
    that many epochs of `steps_per_epoch` steps; `steps_per_epoch`, `steps` (and the optimiser's
    `lr_milestones`) are filled in from the training set when the run starts (`resolve_epochs`)
    and config.json records them. epochs = 0: `steps` as given (a step count instead of epochs).
    """

    epochs: int = 0
    steps_per_epoch: int = 0  # 0: not resolved yet (ceil(training sequences / batch))
    steps: int = 0
    log_every: int = 50
    val_every: int = 500
    ckpt_every: int = 500
    keep_checkpoints: int = 3
    # > 0: every checkpoint at a multiple of this many steps is kept as well (a multiple of
    # ckpt_every to mean anything); 0: only the last keep_checkpoints and the best.
    keep_every: int = 0
    # Wall-clock limit of one invocation of the trainer, in minutes (0: none). Reached, the run
    # stops after the current step as if it were the last one (validation, checkpoint,
    # artefacts); fixed-budget comparisons (experiments/phase1_study.py) use it.
    time_limit_minutes: float = 0.0


@dataclass(frozen=True)
class SkelTrainConfig:
    """Phase 1: keypoint detector + affinity (Eq. 23)."""

    data: DataConfig = field(default_factory=DataConfig)
    model: DetectorConfig = field(default_factory=DetectorConfig)
    weights: LossWeights = field(default_factory=LossWeights)
    # The release's phase-1 recipe: the default dataset's decay epochs (`skel_preset` sets each
    # dataset's) and 200 epochs.
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(decay_epochs=(60, 140)))
    loop: LoopConfig = field(default_factory=lambda: LoopConfig(epochs=200))
    seed: int = 0
    val_batches: int = 4
    run: str | None = None  # default: runs/skel-<data>-<timestamp>
    # A run whose trained detector this one starts from (fine-tuning, `--init-from`), with a
    # fresh optimizer; "": the initialisation of `model.init` at `seed`.
    init_from: str = ""


@dataclass(frozen=True)
class DynamicsConfig:
    """Dynamics module of Sec. 4 and Fig. 10-11 (docs/architecture.md §8)."""

    model: str = "nm"  # "nm": rotations + forward kinematics; "vrnn": positional baseline
    latent: int = 128  # D_z
    hidden: int = 512  # D_h
    mlp: int = 128
    posterior_samples: int = 10  # S, best-of-S during training


@dataclass(frozen=True)
class DynTrainConfig:
    """Phase 2: VRNN over the keypoint trajectories of a phase-1 run (Eqs. 3-4)."""

    skel_run: str | None = None  # default: latest phase-1 run of `data.name`
    data: DynDataConfig = field(default_factory=DynDataConfig)
    model: DynamicsConfig = field(default_factory=DynamicsConfig)
    # The release's phase-2 recipe (its opt.pickle for AIST++: 150 epochs, no decay, lr 4e-4, no
    # clipping, Adam created anew every epoch), an epoch ceil(training sequences / batch_size)
    # steps.
    optim: OptimConfig = field(default_factory=OptimConfig)
    loop: LoopConfig = field(default_factory=lambda: LoopConfig(epochs=150))
    # Weight of the KL, itself the mean over batch, time and latent dimension of the
    # per-dimension KL (the release's reduction); 0.003 is the release's, the paper's Table 3
    # prints 1.0.
    kl_weight: float = 0.003
    seed: int = 0
    run: str | None = None
    # A phase-2 run whose trained model this one starts from (fine-tuning, `--init-from`), with
    # a fresh optimizer; "": the initialisation at `seed`.
    init_from: str = ""

    # Top-level fields of the first phase-2 layout, before `data` was a group ("data" then the
    # dataset's name): a config.json of that layout is read into the group, and `--set NAME=V` /
    # `config_io.replace_fields` still take the old names (`config_io.MOVED_FIELDS`).
    MOVED_FIELDS: ClassVar[Mapping[str, str]] = MappingProxyType(
        {
            "data": "data.name",
            "frames": "data.frames",
            "batch_size": "data.batch_size",
            "inputs": "data.inputs",
        }
    )


DYN_INPUTS = ("crop", "sequence")


def check_batch_split(
    batch_size: int,
    parts: int,
    field: str,
    over: str,
    option: str | None = None,
    otherwise: str = "",
) -> None:
    """Refuses a global batch that does not split evenly into `parts` (devices or hosts).

    The one divisibility check of both trainers (`train.parallel.check_batch_size`, over the
    devices) and of the input pipeline (over the hosts, each loading its share).

    Args:
      batch_size: the global batch size B.
      parts: how many equal shares B is split into.
      field: the config field B comes from, named in the message (e.g. "data.batch_size").
      over: what B is split over, for the message (e.g. "2 devices (1 host(s))").
      option: the command-line option that sets B, for the fix (e.g. "--batch-size "); default
        "FIELD to ".
      otherwise: a second fix appended to the message (e.g. ", or run on fewer devices").

    Raises:
      ValueError: B < 1 or B not a multiple of `parts`; the message suggests the nearest one.
    """
    if batch_size >= 1 and batch_size % parts == 0:
        return
    suggestion = max(round(batch_size / parts), 1) * parts
    raise ValueError(
        f"{field} = {batch_size} is the global batch, split evenly over {over}, so it must be a "
        f"positive multiple of {parts}; set {option or field + ' to '}{suggestion} for "
        f"example{otherwise}"
    )


# How often Adam's state restarts: "epoch" (the release) or "never".
OPTIMIZER_RESETS = ("epoch", "never")


def steps_per_epoch(num_sequences: int, batch_size: int) -> int:
    """Optimizer steps in one epoch: ceil(num_sequences / batch_size).

    An epoch is one random crop of every training sequence, shuffled (docs/architecture.md §6b). The
    release ends an epoch with a partial batch; a compiled step has a fixed batch, so here the last
    batch of an epoch is filled with the first crops of the next epoch's shuffle (the crop stream
    runs on without a break, `data.pipeline`): no crop is dropped, and every epoch is ceil(N / B)
    steps (27 sequences at B = 3: 9; 28: 10).
    """
    if num_sequences < 1 or batch_size < 1:
        raise ValueError(
            f"steps_per_epoch needs >= 1 sequence and batch size, got {num_sequences}, {batch_size}"
        )
    return -(-num_sequences // batch_size)


def resolve_epochs(cfg: Any, num_sequences: int, batch_size: int) -> Any:
    """`cfg` (phase 1 or 2) with `loop.steps_per_epoch` from the training set and, for a schedule
    in epochs that is not resolved yet, `loop.steps` and `optim.lr_milestones` from its epochs.

    A configuration already resolved (a resumed run's config.json) keeps its steps, which
    `--steps` may have changed; its steps per epoch must still be those of the data.

    Raises:
      ValueError: the stored steps_per_epoch differs from what the data gives now.
    """
    per_epoch = steps_per_epoch(num_sequences, batch_size)
    loop = cfg.loop
    if loop.steps_per_epoch:
        if loop.steps_per_epoch != per_epoch:
            raise ValueError(
                f"the run was configured with {loop.steps_per_epoch} steps per epoch, but "
                f"{num_sequences} training sequences in batches of {batch_size} give "
                f"{per_epoch}: the dataset changed; start a new run"
            )
        return cfg
    loop = dataclasses.replace(loop, steps_per_epoch=per_epoch)
    if loop.epochs <= 0:
        return dataclasses.replace(cfg, loop=loop)
    loop = dataclasses.replace(loop, steps=loop.epochs * per_epoch)
    milestones = tuple(e * per_epoch for e in cfg.optim.decay_epochs)
    return dataclasses.replace(
        cfg, loop=loop, optim=dataclasses.replace(cfg.optim, lr_milestones=milestones)
    )


def milestone_fractions(cfg: SkelTrainConfig) -> tuple[float, ...]:
    """Where the learning-rate decays sit, as fractions of the run."""
    if cfg.loop.epochs > 0:
        return tuple(e / cfg.loop.epochs for e in cfg.optim.decay_epochs)
    return tuple(m / cfg.loop.steps for m in cfg.optim.lr_milestones)


def with_steps(cfg: SkelTrainConfig, steps: int) -> SkelTrainConfig:
    """`cfg` as a run of `steps` optimizer steps (epochs = 0), each learning-rate decay at the
    fraction of the run where `cfg` had it (`--steps`, `--fit-minutes`)."""
    milestones = tuple(round(f * steps) for f in milestone_fractions(cfg))
    return replace_fields(cfg, epochs=0, steps=steps, lr_milestones=milestones)


# Share of a fitted budget kept for what is not a train step: compiling, validations, figures,
# checkpoints and the final export; above the share the 6,000-step synth-hand cpu run spent on
# them (its wall time against its steps' time: experiments/results/archive/
# train_skel_synth-hand.json).
FIT_OVERHEAD = 0.08


def fit_schedule(
    cfg: SkelTrainConfig,
    seconds_per_step: float,
    minutes: float,
    spent_seconds: float = 0.0,
    overhead: float = FIT_OVERHEAD,
) -> SkelTrainConfig:
    """`cfg` with as many steps as fit `minutes` of wall time, the schedule scaled with them.

    steps = floor((60 minutes - spent_seconds) / (seconds_per_step (1 + overhead))), counted in
    steps (epochs = 0); every learning-rate decay keeps its fraction of the run, and
    `time_limit_minutes` becomes what is left of the budget, so a slower step than measured
    stops the run in time instead of overrunning it.

    Args:
      cfg: the configuration to fit (its steps and lr_milestones give the schedule's shape).
      seconds_per_step: the measured wall time of one train step (data included).
      minutes: the whole budget of the command.
      spent_seconds: the part of it already used (measuring the step).
      overhead: share of the time kept for compiling, validation, checkpoints and export.

    Raises:
      ValueError: a non-positive input, or a budget too small for one step after each
        milestone.
    """
    if not (seconds_per_step > 0 and minutes > 0 and spent_seconds >= 0 and overhead >= 0):
        raise ValueError(
            f"fit_schedule needs seconds_per_step > 0, minutes > 0, spent_seconds >= 0 and "
            f"overhead >= 0; got {seconds_per_step}, {minutes}, {spent_seconds}, {overhead}"
        )
    left = 60.0 * minutes - spent_seconds
    steps = int(max(left, 0.0) // (seconds_per_step * (1.0 + overhead)))
    milestones = with_steps(cfg, steps).optim.lr_milestones if steps > 0 else ()
    if (
        steps < len(milestones) + 2
        or len(set(milestones)) < len(milestones)
        or min(milestones, default=1) < 1
    ):
        raise ValueError(
            f"{minutes} minutes fit only {steps} steps of {seconds_per_step:.3g} s (after "
            f"{spent_seconds:.0f} s spent measuring); give more minutes or a smaller preset"
        )
    return replace_fields(with_steps(cfg, steps), time_limit_minutes=left / 60.0)


# --- presets ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Preset:
    """One named scale of both phases, as values: the fields it sets over a dataset's own
    configuration, by dotted name as `--set` spells them (`config_io.replace_paths`).

    Why each value is what it is, and what was measured against it, is
    experiments/results/presets.md.

    Attributes:
      skel: phase 1's changes (`skel_preset`).
      dyn: phase 2's changes (`dyn_preset`).
      skel_per_data: further phase-1 changes for one dataset, {dataset: changes}.
    """

    skel: Mapping[str, Any] = field(default_factory=dict)
    dyn: Mapping[str, Any] = field(default_factory=dict)
    skel_per_data: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)


PRESETS: dict[str, Preset] = {
    # The paper's network (G=64, C=128) and the release's recipe, per dataset (Tables 3-8).
    "default": Preset(),
    # Sized for 2 CPU cores (12 frames of 32^3 per phase-1 step instead of 30 of 64^3), with the
    # phase-1 recipe that measured better there: a step count, lr 1e-3, one Adam state, every
    # step clipped at global norm 1.0, 0.25x and 0.1x at the milestones.
    "cpu": Preset(
        skel={
            "data.grid": 32,
            "data.frames": 6,
            "data.batch_size": 2,
            "model.grid": 32,
            "model.channels": 16,
            "model.hourglass_channels": (16, 24, 32),
            "optim.learning_rate": 1e-3,
            "optim.lr_milestones": (1400, 1900),
            "optim.clip_norm": 1.0,
            "optim.optimizer_reset": "never",
            "loop.epochs": 0,
            "loop.steps": 2200,
            "loop.log_every": 25,
            "loop.val_every": 200,
            "loop.ckpt_every": 200,
            "val_batches": 8,
        },
        skel_per_data={"synth-hand": {"weights.vol": 10.0, "model.keypoint_temperature": 0.5}},
        # A step count instead of epochs: a synthetic body's 27 training sequences are 2 steps an
        # epoch at B = 16, so the release's 150 epochs would be 300 steps. The release's KL
        # weight and optimizer stay.
        dyn={
            "model.latent": 32,
            "model.hidden": 128,
            "model.mlp": 64,
            "loop.epochs": 0,
            "loop.steps": 3000,
        },
    ),
    # For tests: the smallest shapes that train, a few steps. K = 6 is below every dataset's K.
    # The CPU's taps-stacked convolutions compile quickest, and a tiny run is nearly all
    # compilation.
    "tiny": Preset(
        skel={
            "data.grid": 16,
            "data.frames": 4,
            "data.batch_size": 2,
            "model.grid": 16,
            "model.num_keypoints": 6,
            "model.channels": 8,
            "model.hourglass_channels": (8, 8, 8),
            "model.conv_form": "stacked",
            "optim.lr_milestones": (10, 15),
            "loop.epochs": 0,
            "loop.steps": 20,
            "loop.log_every": 5,
            "loop.val_every": 10,
            "loop.ckpt_every": 10,
            "val_batches": 1,
        },
        dyn={
            "data.frames": 6,
            "data.batch_size": 4,
            "model.latent": 4,
            "model.hidden": 16,
            "model.mlp": 16,
            "model.posterior_samples": 3,
            "loop.epochs": 0,
            "loop.steps": 10,
            "loop.log_every": 5,
            "loop.val_every": 5,
            "loop.ckpt_every": 5,
        },
    ),
}


def preset_of(name: str) -> Preset:
    """The preset `name` of `PRESETS`; an unknown name lists the valid ones."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; valid presets: {', '.join(PRESETS)}")
    return PRESETS[name]


def skel_preset(data: str = "synth-hand", preset: str = "default") -> SkelTrainConfig:
    """Phase-1 configuration of dataset `data` at scale `preset`.

    The dataset's own configuration is the paper's network and the release's recipe with its
    `DatasetSpec` (G=64, C=128, batch 3, T=10; the dataset's epochs, decay epochs and loss
    weights, Adam at 4e-4 restarted every epoch, no clipping; a dataset with `DatasetSpec.steps`,
    the `capture` spec, counts that many steps instead, with one Adam state); the preset's
    `Preset.skel` and `Preset.skel_per_data` values are set over it.
    """
    spec = dataset_spec(data)
    chosen = preset_of(preset)
    cfg = SkelTrainConfig(
        data=DataConfig(name=data, sample_rate=spec.sample_rate),
        model=DetectorConfig(num_keypoints=spec.num_keypoints, sigma_g=spec.sigma_g),
        weights=LossWeights(vol=spec.w_vol, traj=spec.w_traj, local=spec.w_local),
        optim=OptimConfig(decay_epochs=spec.decay_epochs),
        loop=LoopConfig(epochs=spec.epochs),
    )
    if spec.steps:
        cfg = replace_fields(with_steps(cfg, spec.steps), optimizer_reset="never")
    return replace_paths(cfg, {**chosen.skel, **chosen.skel_per_data.get(data, {})})


def dyn_preset(data: str = "synth-hand", preset: str = "default") -> DynTrainConfig:
    """Phase-2 configuration of dataset `data` at scale `preset`: the release's (batch 16 of 20
    frames, 150 epochs, Adam at 4e-4 restarted every epoch, KL weight 0.003) with the preset's
    `Preset.dyn` values set over it."""
    dataset_spec(data)
    return replace_paths(DynTrainConfig(data=DynDataConfig(name=data)), preset_of(preset).dyn)
