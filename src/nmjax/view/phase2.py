"""The views of what the phase-2 model does: a phase-2 run (`nmjax train-dyn`, model "nm") shows
the sequence's conditioning frames and S generated continuations side by side, and below them
the interpolation of a gap by the model beside the Lerp and Slerp baselines (and the positional
VRNN when a run of it lies beside); a retarget output folder (`nmjax retarget`) shows the posed
target mesh of every frame with its retargeted joints, beside the source motion. The tasks run
through `nmjax.tasks`; nothing here runs a model of its own."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from nmjax.view.draw import (
    GENERATED_BONE_COLOR,
    MESH_COLOR,
    PANEL_SPACING,
    clamp_frame,
)
from nmjax.view.viewer import Pose, Viewer


@dataclasses.dataclass
class Phase2Data:
    """The models and keypoints a phase-2 view runs the tasks with.

    Attributes:
      run, skel_run: the phase-2 run and the phase-1 run it was trained on.
      keypoints: {sequence: (S, K, 4)} the phase-1 run's exported keypoints of the split.
      parents: (K,) the pruned tree of the phase-1 run; keep: (K,) its kept nodes; root.
      model: (graphdef, state) of the "nm" dynamics; vrnn: that of the positional baseline run
        found beside it, or None.
      up_axis: of the phase-1 run's data configuration.
    """

    run: Path
    skel_run: Path
    keypoints: dict[str, np.ndarray]
    parents: np.ndarray
    keep: np.ndarray
    root: int
    model: tuple[Any, Any]
    vrnn: tuple[Any, Any] | None
    up_axis: int

    @property
    def methods(self) -> list[str]:
        """The interpolation methods shown, in `tasks.Interpolators` names."""
        from nmjax import tasks

        return tasks.interpolation_methods(self.vrnn is not None)

    def generate(
        self, name: str, cond: int, gen: int, samples: int, seed: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """(observed (F, K, 4), samples (S, F, K, 4)), F = cond + gen: the sequence's first F
        frames (held at its last) and S futures of its first `cond` frames (`tasks`)."""
        import jax
        import jax.numpy as jnp

        from nmjax import tasks

        _, observed = tasks.pick_inputs(self.keypoints, 1, cond + gen, [name])
        futures, _ = tasks.generate_jit(
            *self.model,
            jnp.asarray(observed[:, :cond]),
            jax.random.key(seed),
            num_frames=gen,
            num_samples=samples,
        )
        return observed[0], np.asarray(futures)[0]

    def interpolate(
        self, name: str, gap: int, trajectories: int, seed: int
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """(truth (gap + 1, K, 4), {method: (gap + 1, K, 4)}) between frames 0 and `gap`."""
        import jax

        from nmjax import tasks

        _, truth = tasks.pick_inputs(self.keypoints, 1, gap + 1, [name])
        interp = tasks.Interpolators(self.model, self.vrnn, trajectories)
        key = jax.random.key(seed)
        return truth[0], {
            m: interp.run(m, truth[:, 0], truth[:, -1], gap, key)[0] for m in self.methods
        }


def read_phase2(run: str | Path, split: str = "test") -> Phase2Data:
    """A phase-2 ("nm") run's view data: its models, phase-1 keypoints and skeleton.

    Raises:
      FileNotFoundError, ValueError: as `trained.phase2_runs`, `trained.load_phase2` and the phase-1
        readers (a missing export names the command that writes it).
    """
    from flax import nnx

    from nmjax import run_folder
    from nmjax.config import DynTrainConfig, SkelTrainConfig
    from nmjax.train import trained

    run = Path(run)
    model_kind = run_folder.load_config(run, DynTrainConfig).model.model
    if model_kind != "nm":
        raise ValueError(
            f"--run {run} is a '{model_kind}' run; view the Neural Marionette ('nm') run of the "
            "same phase-1 run instead (its positional VRNN baseline is found beside it)"
        )
    _, skel_run, vrnn_run = trained.phase2_runs(run, None)
    model, _, _ = trained.load_phase2(run)
    keypoints = run_folder.load_trajectories(skel_run, split)
    skeleton = run_folder.read_skeleton(skel_run)
    parents, keep = run_folder.pruned_skeleton(skel_run)
    vrnn = None if vrnn_run is None else nnx.split(trained.restore_dynamics(vrnn_run))
    return Phase2Data(
        run=run,
        skel_run=skel_run,
        keypoints=keypoints,
        parents=parents,
        keep=keep,
        root=skeleton.root,
        model=nnx.split(model),
        vrnn=vrnn,
        up_axis=run_folder.load_config(skel_run, SkelTrainConfig).data.up_axis,
    )


class Phase2Viewer(Viewer):
    """The tasks of a phase-2 run on one sequence (see the module docstring).

    Top row: the sequence's first `cond + gen` frames ("observed") and `samples` generated
    continuations of its first `cond`; bottom row: frames 0..gap of the sequence ("truth") and
    each interpolation method between its frames 0 and `gap`. Bones are orange on the frames a
    method generated. A dropdown picks the sequence; the tasks then run on it again.
    """

    kind = "phase-2 run"

    def __init__(
        self,
        server: Any,
        data: Phase2Data,
        seq: str,
        *,
        cond: int = 5,
        gen: int = 25,
        samples: int = 3,
        gap: int = 10,
        trajectories: int = 16,
        seed: int = 0,
    ):
        super().__init__(server, str(data.run), data.up_axis)
        self.data = data
        self.cond, self.gen, self.samples, self.gap = cond, gen, samples, gap
        self.trajectories, self.seed = trajectories, seed
        rows = {
            "generate": ["observed"] + [f"sample {s + 1}" for s in range(samples)],
            "interpolate": ["truth", *data.methods],
        }
        self.panels: dict[str, Pose] = {}
        self.motions: dict[str, np.ndarray] = {}
        for row, (task, labels) in enumerate(rows.items()):
            for column, label in enumerate(labels):
                prefix = f"/{task}/{label.replace(' ', '_')}"
                offset = PANEL_SPACING * (column * self.right - row * self.up)
                frame = self.add("add_frame", prefix, show_axes=False, position=offset)
                self.add(
                    "add_label",
                    f"{prefix}/label",
                    text=f"{label}" if row == 0 else f"{label} (gap {gap})",
                    position=tuple(1.15 * self.up),
                    anchor="bottom-center",
                )
                self.panels[prefix] = Pose(self, prefix, data.parents, data.root, keep=data.keep)
                self.toggle(f"{task}: {label}", lambda frame=frame: [frame])
        width = PANEL_SPACING * (max(map(len, rows.values())) - 1)
        self.look_at(width / 2.0 * self.right - PANEL_SPACING / 2.0 * self.up, width + 2.0)
        with self.controls:
            self.sequence = server.gui.add_dropdown(
                "sequence", tuple(sorted(data.keypoints)), initial_value=seq, order=-1.0
            )
        self.sequence.on_update(lambda _: self.load(self.sequence.value))
        self.load(seq)

    @property
    def num_frames(self) -> int:
        return max(len(m) for m in self.motions.values())

    def load(self, name: str) -> None:
        """Runs generation and interpolation on sequence `name` and draws frame 0."""
        with self._lock:
            observed, futures = self.data.generate(
                name, self.cond, self.gen, self.samples, self.seed
            )
            truth, methods = self.data.interpolate(name, self.gap, self.trajectories, self.seed)
            self.motions = {"/generate/observed": observed, "/interpolate/truth": truth}
            for s, future in enumerate(futures):
                self.motions[f"/generate/sample_{s + 1}"] = future
            for method, motion in methods.items():
                self.motions[f"/interpolate/{method}"] = motion
            self.reset_frames()

    def draw(self, t: int) -> None:
        for prefix, pose in self.panels.items():
            motion = self.motions[prefix]
            frame = clamp_frame(t, len(motion))
            if prefix.startswith("/generate/sample"):
                generated = frame >= self.cond
            else:
                generated = prefix.startswith("/interpolate/") and not prefix.endswith("truth")
                generated = generated and 0 < frame < self.gap
            pose.show(motion[frame], GENERATED_BONE_COLOR if generated else None)


class RetargetViewer(Viewer):
    """An `nmjax retarget` output: the posed target mesh with its retargeted joints, and the
    source motion beside it (its normalised frame scaled to the mesh's size)."""

    kind = "retarget output"

    def __init__(self, server: Any, folder: Path, data: dict[str, Any], up_axis: int):
        super().__init__(server, str(folder), up_axis)
        self.vertices = data["vertices"]
        self.joints = data["joints"]
        lo = self.vertices.reshape(-1, 3).min(axis=0)
        hi = self.vertices.reshape(-1, 3).max(axis=0)
        centre, extent = (lo + hi) / 2.0, float(np.max(hi - lo))
        parents = np.asarray(data["parents"])
        root = int(np.flatnonzero(parents == np.arange(len(parents)))[0])
        source = data["source_keypoints"]
        source_lo = source[..., :3].reshape(-1, 3).min(axis=0)
        source_hi = source[..., :3].reshape(-1, 3).max(axis=0)
        scale = extent / max(float(np.max(source_hi - source_lo)), 1e-6)
        # The source in its own normalised frame, scaled to the target's size, to its left.
        self.source = source.copy()
        self.source[..., :3] = (
            (source[..., :3] - (source_lo + source_hi) / 2.0) * scale
            + centre
            - 1.4 * extent * self.right
        )
        radius = 0.02 * extent
        self.mesh = self.add(
            "add_mesh_simple",
            "/target/mesh",
            vertices=self.vertices[0],
            faces=data["faces"],
            color=MESH_COLOR,
            opacity=0.75,
            side="double",
        )
        self.target = Pose(self, "/target", parents, root, radius=radius)
        self.source_pose = Pose(self, "/source", parents, root, radius=radius)
        top = (0.5 * extent + radius) * self.up
        self.add(
            "add_label",
            "/target/label",
            text="retargeted",
            position=tuple(centre + top),
            anchor="bottom-center",
        )
        self.add(
            "add_label",
            "/source/label",
            text=f"source {data['source']}",
            position=tuple(centre - 1.4 * extent * self.right + top),
            anchor="bottom-center",
        )
        self.toggle("mesh", lambda: [self.mesh])
        self.toggle("retargeted joints", lambda: self.target.handles)
        self.toggle("source", lambda: [*self.source_pose.handles, self.nodes["/source/label"]])
        self.look_at(centre - 0.7 * extent * self.right, 2.6 * extent)
        self.reset_frames()

    @property
    def num_frames(self) -> int:
        return len(self.vertices)

    def draw(self, t: int) -> None:
        self.mesh.vertices = self.vertices[t]
        self.target.show(self.joints[t])
        self.source_pose.show(self.source[clamp_frame(t, len(self.source))])
