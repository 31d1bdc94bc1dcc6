"""The view of a phase-1 run (`nmjax train-skel`): one sequence of a split with its points (or
occupied voxels), the detector's keypoints of every frame (colour by index, size by intensity
alpha, the nodes the skeleton prunes in grey), the bones of the pruned skeleton between kept
nodes with the root marked, the ground-truth joints and tree where the dataset has them, the
refined skeleton where `nmjax refine` refined the sequence (its joints and bones, constant in
length), and the learned affinity (the influence max_n A_n of docs/architecture.md §7) as the
opacity of a line between every pair of keypoints."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from nmjax.view.draw import (
    AFFINITY_COLOR,
    BODY_COLOR,
    KEYPOINT_RADIUS,
    POINT_SIZE,
    REFINED_COLOR,
    TRUTH_COLOR,
    affinity_pairs,
    cylinder_transforms,
    unit_cylinder,
)
from nmjax.view.viewer import Pose, Viewer


@dataclasses.dataclass
class Phase1Data:
    """Everything a phase-1 view draws, read from the run folder and its dataset.

    Attributes:
      run: the run folder; split: the split whose sequences are shown.
      keypoints: {sequence: (S, K, 4)} the exported keypoints (`run_folder.load_trajectories`).
      parents: (K,) the pruned tree (`run_folder.pruned_skeleton`), keep: (K,) its kept nodes.
      root: the root keypoint.
      influence: (K, K) max_n A_n of the learned affinity, None when the run has no affinity.npy.
      sequences: {name: `datasets.Sequence`}, None when the dataset cannot be read here.
      truth_parents: (J,) the dataset's joint tree (meta.json), None when it has none.
      sample_rate, grid, up_axis: of the run's data configuration.
      refined: {sequence: `run_folder.read_refined`'s arrays} of the sequences `nmjax refine`
        refined ({} when none).
      note: why a layer is missing, for the user ("" when none is).
    """

    run: Path
    split: str
    keypoints: dict[str, np.ndarray]
    parents: np.ndarray
    keep: np.ndarray
    root: int
    influence: np.ndarray | None
    sequences: dict[str, Any] | None
    truth_parents: np.ndarray | None
    sample_rate: int
    grid: int
    up_axis: int
    refined: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)
    note: str = ""

    def frames(self, name: str) -> tuple[np.ndarray | None, np.ndarray | None]:
        """(points (S, N, 3), joints (S, J, 3)) of sequence `name` in the keypoints' normalised
        coordinates (`trained.sequence_points`); None where the data is missing.

        Raises:
          ValueError: the keypoints were exported from a different number of frames.
        """
        from nmjax import run_folder
        from nmjax.train import trained

        seq = None if self.sequences is None else self.sequences.get(name)
        if seq is None:
            return None, None
        points, joints = trained.sequence_points(seq, self.sample_rate)
        if len(points) != len(self.keypoints[name]):
            raise ValueError(
                f"{run_folder.keypoints_file(self.run, self.split)}[{name!r}] has "
                f"{len(self.keypoints[name])} frames, the dataset's sequence {len(points)}; "
                f"re-export with `nmjax export-keypoints --run {self.run}`"
            )
        return points, joints


def read_phase1(run: str | Path, split: str = "test") -> Phase1Data:
    """A finished phase-1 run's view data (keypoints, skeleton, affinity, dataset).

    Raises:
      FileNotFoundError: no skeleton.json or keypoints_<split>.npz yet (names the command).
      ValueError: damaged run files.
    """
    from nmjax import run_folder
    from nmjax.config import SkelTrainConfig
    from nmjax.data import datasets, layout
    from nmjax.skeleton import influence

    run = Path(run)
    cfg = run_folder.load_config(run, SkelTrainConfig)
    keypoints = run_folder.load_trajectories(run, split)
    skeleton = run_folder.read_skeleton(run)
    parents, keep = run_folder.pruned_skeleton(run)
    num = len(parents)
    for name, x in keypoints.items():
        if x.shape[1] != num:
            raise ValueError(
                f"{run_folder.keypoints_file(run, split)}[{name!r}] has {x.shape[1]} keypoints, "
                f"{run / run_folder.SKELETON_FILE} {num}; re-export with `nmjax export-keypoints "
                f"--run {run}`"
            )
    notes = []
    try:
        affinity, _ = run_folder.read_skeleton_inputs(run)
        strength = influence(affinity)
    except FileNotFoundError as err:
        strength = None
        notes.append(f"no affinity layer ({' '.join(str(err).split())})")
    if strength is not None and strength.shape != (num, num):
        raise ValueError(
            f"{run / run_folder.AFFINITY_FILE} is for K={len(strength)} keypoints, the skeleton "
            f"has {num}; re-extract it with `nmjax extract-skeleton --run {run}`"
        )
    data = cfg.data
    try:
        sequences = {s.name: s for s in datasets.load_sequences(data.name, split, data.root)}
        truth = layout.read_meta(data.name, data.root).get("parents")
    except FileNotFoundError as err:
        sequences, truth = None, None
        notes.append(f"no points or joints ({' '.join(str(err).split())})")
    return Phase1Data(
        run=run,
        split=split,
        keypoints=keypoints,
        parents=parents,
        keep=keep,
        root=skeleton.root,
        influence=strength,
        sequences=sequences,
        truth_parents=None if truth is None else np.asarray(truth, np.int64),
        sample_rate=data.sample_rate,
        grid=data.grid,
        up_axis=data.up_axis,
        refined=read_refined_sequences(run, split, keypoints),
        note="; ".join(notes),
    )


def read_refined_sequences(
    run: Path, split: str, keypoints: dict[str, np.ndarray]
) -> dict[str, dict[str, Any]]:
    """{sequence: refined arrays} of the sequences of `split` that `nmjax refine` refined.

    Raises:
      ValueError: a damaged refined file, or one of another number of frames than the keypoints.
    """
    from nmjax import run_folder

    out = {}
    for name in run_folder.refined_sequences(run, split):
        arrays = run_folder.read_refined(run, split, name)
        if name not in keypoints or arrays is None:
            continue
        if len(arrays["positions"]) != len(keypoints[name]):
            raise ValueError(
                f"{run_folder.refined_file(run, split, name)} has {len(arrays['positions'])} "
                f"frames, the keypoints {len(keypoints[name])}; refine it again with `nmjax "
                f"refine --run {run} --split {split} --seq {name}`"
            )
        out[name] = arrays
    return out


class Phase1Viewer(Viewer):
    """One sequence of a phase-1 run (see the module docstring); a dropdown picks it."""

    kind = "phase-1 run"

    def __init__(self, server: Any, data: Phase1Data, seq: str):
        super().__init__(server, str(data.run), data.up_axis)
        self.data = data
        self.points: np.ndarray | None = None
        self.joints: np.ndarray | None = None
        self.body = self.add(
            "add_point_cloud",
            "/body/points",
            points=np.zeros((1, 3), np.float32),
            colors=BODY_COLOR,
            point_size=POINT_SIZE,
            point_shape="circle",
        )
        self.voxels = self.add(
            "add_point_cloud",
            "/body/voxels",
            points=np.zeros((1, 3), np.float32),
            colors=BODY_COLOR,
            point_size=2.0 / data.grid,
            point_shape="square",
            point_shading="flat",
        )
        self.pose = Pose(self, "", data.parents, data.root, keep=data.keep)
        self.truth: Pose | None = None
        self.refined: Pose | None = None
        self.affinity = None
        if data.influence is not None:
            self.affinity_pairs, strength = affinity_pairs(data.influence)
            count = len(self.affinity_pairs)
            cylinder = unit_cylinder()
            self.affinity = self.add(
                "add_batched_meshes_simple",
                "/affinity",
                vertices=cylinder.vertices,
                faces=cylinder.faces,
                batched_wxyzs=np.tile([1.0, 0.0, 0.0, 0.0], (count, 1)),
                batched_positions=np.zeros((count, 3)),
                batched_scales=np.ones((count, 3)),
                batched_colors=AFFINITY_COLOR,
                batched_opacities=strength.astype(np.float32),
                lod="off",
            )
        gui = server.gui
        with self.controls:
            self.sequence = gui.add_dropdown(
                "sequence", tuple(sorted(data.keypoints)), initial_value=seq, order=-1.0
            )
        with self.layers:
            self.body_mode = gui.add_dropdown("body as", ("points", "voxels"))
        if data.note:
            gui.add_markdown(f"*{data.note}*")
        self.toggle("body", self._body_handles)
        self.toggle("keypoints", lambda: [self.pose.keypoints])
        self.toggle("skeleton", lambda: self.pose.skeleton_handles)
        self.toggle("ground truth", self._truth_handles)
        self.toggle("refined skeleton", self._refined_handles)
        self.toggle("affinity", lambda: [] if self.affinity is None else [self.affinity], False)
        self.body_mode.on_update(lambda _: self._switch_body())
        self.sequence.on_update(lambda _: self.load(self.sequence.value))
        self.load(seq)

    @property
    def num_frames(self) -> int:
        return len(self.data.keypoints[self.sequence.value])

    def _body_handles(self) -> list[Any]:
        return [self.voxels if self.body_mode.value == "voxels" else self.body]

    def _truth_handles(self) -> list[Any]:
        return [] if self.truth is None else self.truth.handles

    def _refined_handles(self) -> list[Any]:
        return [] if self.refined is None else self.refined.handles

    def _switch_body(self) -> None:
        voxels = self.body_mode.value == "voxels"
        self.body.visible = self.toggles["body"].value and not voxels
        self.voxels.visible = self.toggles["body"].value and voxels
        self.show(self.frame.value)

    def load(self, name: str) -> None:
        """Reads sequence `name`'s points and joints, aims the camera and draws frame 0."""
        with self._lock:
            self.points, self.joints = self.data.frames(name)
            if self.joints is not None and self.truth is None:
                parents = self.data.truth_parents
                if parents is None or len(parents) != self.joints.shape[1]:
                    parents = np.arange(self.joints.shape[1])  # joints without a known tree
                self.truth = Pose(
                    self,
                    "/truth",
                    parents,
                    int(np.flatnonzero(parents == np.arange(len(parents)))[0]),
                    colors=TRUTH_COLOR,
                    bone_color=TRUTH_COLOR,
                    radius=0.6 * KEYPOINT_RADIUS,
                    mark_root=False,
                )
            for handle in self._truth_handles():
                handle.visible = self.toggles["ground truth"].value and self.joints is not None
            refined = self.data.refined.get(name)
            if refined is not None and self.refined is None:
                # Every refined sequence of a run has the run's kept tree.
                self.refined = Pose(
                    self,
                    "/refined",
                    refined["parents"],
                    0,
                    colors=REFINED_COLOR,
                    bone_color=REFINED_COLOR,
                    radius=0.7 * KEYPOINT_RADIUS,
                )
            for handle in self._refined_handles():
                handle.visible = self.toggles["refined skeleton"].value and refined is not None
            self._switch_body()
            cloud = self.data.keypoints[name][..., :3] if self.points is None else self.points
            lo, hi = cloud.reshape(-1, 3).min(axis=0), cloud.reshape(-1, 3).max(axis=0)
            self.look_at((lo + hi) / 2.0, float(np.max(hi - lo)))
            self.reset_frames()

    def draw(self, t: int) -> None:
        keypoints = self.data.keypoints[self.sequence.value][t]
        self.pose.show(keypoints)
        if self.points is not None:
            if self.body_mode.value == "voxels":
                from nmjax.data.voxelize import voxelize
                from nmjax.metrics import voxel_points

                self.voxels.points = voxel_points(voxelize(self.points[t], self.data.grid))
            else:
                self.body.points = self.points[t]
        if self.truth is not None and self.joints is not None:
            self.truth.show(self.joints[t])
        refined = self.data.refined.get(self.sequence.value)
        if self.refined is not None and refined is not None:
            self.refined.show(refined["positions"][t])
        if self.affinity is not None:
            mu = keypoints[:, :3]
            centres, wxyzs, lengths = cylinder_transforms(
                mu[self.affinity_pairs[:, 0]], mu[self.affinity_pairs[:, 1]]
            )
            width = np.full(len(lengths), 0.15 * KEYPOINT_RADIUS)
            self.affinity.batched_positions = centres
            self.affinity.batched_wxyzs = wxyzs
            self.affinity.batched_scales = np.stack([width, width, lengths], axis=1)
