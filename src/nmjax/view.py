"""`nmjax view`: a run folder as a 3D scene in the browser, frame by frame (viser).

Four kinds of input, told apart by what they hold:

- a phase-1 run (`nmjax train-skel`): one sequence of a split with its points (or occupied
  voxels), the detector's keypoints of every frame (colour by index, size by intensity alpha,
  the nodes the skeleton prunes in grey), the bones of the pruned skeleton between kept nodes
  with the root marked, the ground-truth joints and tree where the dataset has them, and the
  learned affinity (the influence max_n A_n of DESIGN section 7) as the opacity of a line between
  every pair of keypoints;
- a phase-2 run (`nmjax train-dyn`, model "nm"): the sequence's conditioning frames and S
  generated continuations side by side, and below them the interpolation of a gap by the model
  beside the Lerp and Slerp baselines (and the positional VRNN when a run of it lies beside);
- a retarget output folder (`nmjax retarget`): the posed target mesh of every frame with its
  retargeted joints, beside the source motion;
- a glTF file written by `nmjax export` (.glb / .gltf): its skeleton and skinned mesh posed at
  every key of its animation by glTF's own rules (`nmjax.export.gltf.read`), so a file can be
  checked before it is sent on.

Everything drawn comes from the run-folder readers (`nmjax.runs`) and the task functions
(`nmjax.tasks`); nothing here runs a model of its own. viser is imported only when a viewer
starts (`pip install -e '.[view]'`), so the rest of nmjax never needs it.
"""

from __future__ import annotations

import colorsys
import dataclasses
import socket
import threading
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

EXTRA = "view"  # the optional dependency group that installs viser
UP_AXES = ("x", "y", "z")

GREY = (160, 160, 160)  # pruned keypoints
BONE_COLOR = (40, 40, 40)
GENERATED_BONE_COLOR = (230, 110, 20)  # bones of frames the model generated
ROOT_COLOR = (20, 20, 20)  # a wire ball around the root keypoint
TRUTH_COLOR = (30, 150, 60)
BODY_COLOR = (120, 160, 210)
AFFINITY_COLOR = (50, 50, 190)
MESH_COLOR = (200, 180, 150)

KEYPOINT_RADIUS = 0.035  # in the normalised cube [-1, 1)^3
POINT_SIZE = 0.012
PANEL_SPACING = 2.6  # between the centres of side-by-side motions (each fills a 2-wide cube)
MIN_SIZE = 0.3  # radius of an alpha = 0 keypoint, as a fraction of an alpha = 1 one


def import_viser():
    """The viser module, or an ImportError whose message names the extra that installs it."""
    try:
        import viser
    except ImportError as err:
        raise ImportError(
            f"nmjax view needs viser; install it with `pip install -e '.[{EXTRA}]'`"
        ) from err
    return viser


# --- what is drawn: plain functions of arrays ---------------------------------------------------


def keypoint_colors(num: int, keep: np.ndarray | None = None) -> np.ndarray:
    """(K, 3) uint8 colours by keypoint index, GREY where `keep` (K,) is False.

    Hues step by the golden ratio, so neighbouring indices get far-apart colours.
    """
    hues = (np.arange(num) * 0.618033988749895) % 1.0
    colors = np.array([colorsys.hsv_to_rgb(h, 0.8, 0.92) for h in hues]) * 255.0
    colors = np.round(colors).astype(np.uint8).reshape(num, 3)
    if keep is not None:
        colors[~np.asarray(keep, bool)] = GREY
    return colors


def keypoint_radii(alpha: np.ndarray, radius: float = KEYPOINT_RADIUS) -> np.ndarray:
    """(K,) sphere radii growing linearly with intensity: alpha (K,) in [0, 1] -> radius *
    [MIN_SIZE, 1], so a keypoint that fades out stays visible."""
    return radius * (MIN_SIZE + (1.0 - MIN_SIZE) * np.clip(alpha, 0.0, 1.0))


def bone_pairs(parents: Iterable[int], keep: np.ndarray | None = None) -> np.ndarray:
    """(B, 2) (parent, child) index pairs of a tree, the root's self-link and every child
    outside `keep` (K,) left out. With the parents of `skeleton.prune`, every bone then links two
    kept nodes."""
    parents = np.asarray(list(parents), np.int64)
    keep = np.ones(len(parents), bool) if keep is None else np.asarray(keep, bool)
    children = np.flatnonzero((parents != np.arange(len(parents))) & keep)
    return np.stack([parents[children], children], axis=1).reshape(-1, 2)


def affinity_pairs(influence: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every keypoint pair k < k' and its link strength for drawing the learned affinity.

    Args:
      influence: (K, K) I = max_n A_n (`skeleton.influence`).

    Returns:
      pairs (P, 2), P = K (K - 1) / 2, and strengths (P,) = max(I[k, k'], I[k', k]) divided by
      the largest of them (all zero when the affinity is).
    """
    influence = np.asarray(influence, np.float64)
    first, second = np.triu_indices(len(influence), k=1)
    strength = np.maximum(influence[first, second], influence[second, first])
    top = strength.max(initial=0.0)
    return np.stack([first, second], axis=1), (strength / top if top > 0 else strength)


def cylinder_transforms(
    starts: np.ndarray, ends: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Poses of unit cylinders (axis z, height 1, centred) stretched from `starts` to `ends`.

    Args:
      starts, ends: (P, 3) segment end points.

    Returns:
      centres (P, 3), orientations (P, 4) as quaternions (w, x, y, z) turning +z onto the
      segment direction (half-way quaternion; a segment along -z turns about x), lengths (P,).
    """
    delta = np.asarray(ends, np.float64) - np.asarray(starts, np.float64)
    lengths = np.linalg.norm(delta, axis=-1)
    d = delta / np.maximum(lengths, 1e-12)[:, None]
    d[lengths < 1e-12] = (0.0, 0.0, 1.0)
    # q = (1 + z.d, z x d) normalised is the rotation by the angle between z and d.
    q = np.stack([1.0 + d[:, 2], -d[:, 1], d[:, 0], np.zeros(len(d))], axis=1)
    flip = q[:, 0] < 1e-9
    q[flip] = (0.0, 1.0, 0.0, 0.0)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return (np.asarray(starts) + np.asarray(ends)) / 2.0, q, lengths


def view_axes(up_axis: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(up, towards the viewer, rightwards) unit vectors of a scene whose up axis is `up_axis`.

    Side-by-side motions are laid out rightwards and their rows downwards; the camera looks
    against `towards` (for z up: from -y, x to the right).
    """
    eye = np.eye(3)
    up, towards = eye[up_axis], -eye[(up_axis + 2) % 3]
    return up, towards, np.cross(up, towards)


def clamp_frame(t: int, length: int) -> int:
    """Frame `t` of a motion of `length` frames; a shorter motion holds its last frame."""
    return int(min(max(t, 0), length - 1))


# --- what is drawn: read from the folders -------------------------------------------------------


@dataclasses.dataclass
class Phase1Data:
    """Everything a phase-1 view draws, read from the run folder and its dataset.

    Attributes:
      run: the run folder; split: the split whose sequences are shown.
      keypoints: {sequence: (S, K, 4)} the exported keypoints (`runs.load_trajectories`).
      parents: (K,) the pruned tree (`runs.pruned_skeleton`), keep: (K,) its kept nodes.
      root: the root keypoint.
      influence: (K, K) max_n A_n of the learned affinity, None when the run has no affinity.npy.
      sequences: {name: `datasets.Sequence`}, None when the dataset cannot be read here.
      truth_parents: (J,) the dataset's joint tree (meta.json), None when it has none.
      sample_rate, grid, up_axis: of the run's data configuration.
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
    note: str = ""

    def frames(self, name: str) -> tuple[np.ndarray | None, np.ndarray | None]:
        """(points (S, N, 3), joints (S, J, 3)) of sequence `name` in the keypoints' normalised
        coordinates (`runs.sequence_points`); None where the data is missing.

        Raises:
          ValueError: the keypoints were exported from a different number of frames.
        """
        from nmjax import runs

        seq = None if self.sequences is None else self.sequences.get(name)
        if seq is None:
            return None, None
        points, joints = runs.sequence_points(seq, self.sample_rate)
        if len(points) != len(self.keypoints[name]):
            raise ValueError(
                f"{runs.keypoints_file(self.run, self.split)}[{name!r}] has "
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
    from nmjax import run_folder, runs
    from nmjax.config import SkelTrainConfig
    from nmjax.data import datasets, layout
    from nmjax.skeleton import influence

    run = Path(run)
    cfg = run_folder.load_config(run, SkelTrainConfig)
    keypoints = runs.load_trajectories(run, split)
    skeleton = runs.read_skeleton(run)
    parents, keep = runs.pruned_skeleton(run)
    num = len(parents)
    for name, x in keypoints.items():
        if x.shape[1] != num:
            raise ValueError(
                f"{runs.keypoints_file(run, split)}[{name!r}] has {x.shape[1]} keypoints, "
                f"{run / runs.SKELETON_FILE} {num}; re-export with `nmjax export-keypoints "
                f"--run {run}`"
            )
    notes = []
    try:
        affinity, _ = runs.read_skeleton_inputs(run)
        strength = influence(affinity)
    except FileNotFoundError as err:
        strength = None
        notes.append(f"no affinity layer ({' '.join(str(err).split())})")
    if strength is not None and strength.shape != (num, num):
        raise ValueError(
            f"{run / runs.AFFINITY_FILE} is for K={len(strength)} keypoints, the skeleton has "
            f"{num}; re-extract it with `nmjax extract-skeleton --run {run}`"
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
        note="; ".join(notes),
    )


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
        return ["Ours"] + (["VRNN"] if self.vrnn is not None else []) + ["Lerp", "Slerp"]

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
      FileNotFoundError, ValueError: as `runs.phase2_runs`, `runs.load_phase2` and the phase-1
        readers (a missing export names the command that writes it).
    """
    from flax import nnx

    from nmjax import run_folder, runs
    from nmjax.config import DynTrainConfig, SkelTrainConfig

    run = Path(run)
    model_kind = run_folder.load_config(run, DynTrainConfig).model.model
    if model_kind != "nm":
        raise ValueError(
            f"--run {run} is a '{model_kind}' run; view the Neural Marionette ('nm') run of the "
            "same phase-1 run instead (its positional VRNN baseline is found beside it)"
        )
    _, skel_run, vrnn_run = runs.phase2_runs(run, None)
    model, _, _ = runs.load_phase2(run)
    keypoints = runs.load_trajectories(skel_run, split)
    skeleton = runs.read_skeleton(skel_run)
    parents, keep = runs.pruned_skeleton(skel_run)
    vrnn = None if vrnn_run is None else nnx.split(runs.restore_dynamics(vrnn_run))
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


GLTF_SUFFIXES = (".glb", ".gltf")


def folder_kind(folder: str | Path) -> str:
    """What `folder` holds: "skel" (a phase-1 run), "dyn" (phase 2) or "retarget"; "gltf" for
    a .glb / .gltf file.

    Raises:
      FileNotFoundError: no such folder, or one that is neither a run nor a retarget output.
    """
    from nmjax import run_folder, runs, tasks

    folder = Path(folder)
    if folder.is_file() and folder.suffix.lower() in GLTF_SUFFIXES:
        return "gltf"
    if not folder.is_dir():
        raise FileNotFoundError(
            f"--run {folder} does not exist; give a run folder of `nmjax train-skel` or "
            "`nmjax train-dyn`, an output folder of `nmjax retarget`, or a .glb / .gltf file "
            "of `nmjax export`"
        )
    if (folder / run_folder.CONFIG_FILE).is_file():
        return runs.run_kind(folder)
    if (folder / tasks.RETARGET_FILE).is_file():
        return "retarget"
    raise FileNotFoundError(
        f"--run {folder} holds neither {run_folder.CONFIG_FILE} (a run folder) nor "
        f"{tasks.RETARGET_FILE} (an `nmjax retarget` output); is it an unfinished run?"
    )


# --- the viewer ---------------------------------------------------------------------------------


class Pose:
    """One keypoint set in the scene: spheres sized by alpha, bones, a wire ball on the root.

    Nodes `<prefix>/keypoints` (batched spheres, one instance per keypoint),
    `<prefix>/skeleton/bones` (line segments; absent when the tree keeps no bone) and
    `<prefix>/skeleton/root` (absent without `mark_root`).
    """

    def __init__(
        self,
        viewer: Viewer,
        prefix: str,
        parents: np.ndarray,
        root: int,
        *,
        keep: np.ndarray | None = None,
        colors: np.ndarray | tuple[int, int, int] | None = None,
        bone_color: tuple[int, int, int] = BONE_COLOR,
        radius: float = KEYPOINT_RADIUS,
        mark_root: bool = True,
    ):
        import trimesh

        num = len(parents)
        self.radius, self.root, self.bone_color = radius, root, bone_color
        self.pairs = bone_pairs(parents, keep)
        colors = keypoint_colors(num, keep) if colors is None else colors
        self.colors = np.array(np.broadcast_to(np.asarray(colors, np.uint8), (num, 3)))
        sphere = trimesh.creation.icosphere(subdivisions=2)
        self.keypoints = viewer.add(
            "add_batched_meshes_simple",
            f"{prefix}/keypoints",
            vertices=sphere.vertices,
            faces=sphere.faces,
            batched_wxyzs=np.tile([1.0, 0.0, 0.0, 0.0], (num, 1)),
            batched_positions=np.zeros((num, 3)),
            batched_scales=np.full(num, radius),
            batched_colors=self.colors,
            lod="off",
        )
        self.bones = None
        if len(self.pairs):
            self.bones = viewer.add(
                "add_line_segments",
                f"{prefix}/skeleton/bones",
                points=np.zeros((len(self.pairs), 2, 3)),
                colors=bone_color,
                thickness=radius * 0.35,
            )
        self.root_marker = None
        if mark_root:
            self.root_marker = viewer.add(
                "add_icosphere",
                f"{prefix}/skeleton/root",
                radius=radius * 1.8,
                color=ROOT_COLOR,
                wireframe=True,
                subdivisions=1,
            )

    @property
    def handles(self) -> list[Any]:
        return [h for h in (self.keypoints, self.bones, self.root_marker) if h is not None]

    @property
    def skeleton_handles(self) -> list[Any]:
        return [h for h in (self.bones, self.root_marker) if h is not None]

    def show(self, keypoints: np.ndarray, bone_color: tuple[int, int, int] | None = None) -> None:
        """Moves the nodes to one frame: keypoints (K, 4), or joints (K, 3) drawn at alpha 1."""
        mu = np.asarray(keypoints[:, :3], np.float32)
        alpha = keypoints[:, 3] if keypoints.shape[1] > 3 else np.ones(len(mu))
        self.keypoints.batched_positions = mu
        self.keypoints.batched_scales = keypoint_radii(alpha, self.radius)
        if self.bones is not None:
            color = np.asarray(self.bone_color if bone_color is None else bone_color, np.uint8)
            self.bones.points = mu[self.pairs]
            self.bones.colors = np.broadcast_to(color, (*self.pairs.shape, 3))
        if self.root_marker is not None:
            self.root_marker.position = mu[self.root]


class Viewer:
    """A viser server showing one folder, with the controls every view shares: the frame
    slider, play / pause with a speed in frames per second, and one toggle per layer.

    Subclasses say what they show (`num_frames`, `draw(t)`). `nodes` maps every scene node
    name the viewer made to its handle, `toggles` every layer to its checkbox. Setting
    `frame.value`, from the browser or from Python, redraws.
    """

    kind = ""

    def __init__(self, server: Any, title: str, up_axis: int):
        self.server = server
        self.nodes: dict[str, Any] = {}
        self.toggles: dict[str, Any] = {}  # layer label -> its checkbox
        self.up, self.towards, self.right = view_axes(up_axis)
        self._lock = threading.RLock()
        self._stop = threading.Event()
        server.scene.set_up_direction(tuple(self.up))
        gui = server.gui
        gui.add_markdown(f"**{self.kind}** `{title}`")
        self.controls = gui.add_folder("playback")
        with self.controls:
            self.frame = gui.add_slider("frame", min=0, max=1, step=1, initial_value=0)
            self.playing = gui.add_checkbox("play", False)
            self.fps = gui.add_slider("frames / s", min=1, max=30, step=1, initial_value=10)
        self.layers = gui.add_folder("layers")
        self.frame.on_update(lambda _: self.show(self.frame.value))
        self._player = threading.Thread(target=self._play, name="nmjax-view-play", daemon=True)
        self._player.start()

    @property
    def num_frames(self) -> int:
        raise NotImplementedError

    def draw(self, t: int) -> None:
        raise NotImplementedError

    def add(self, method: str, name: str, **kwargs: Any) -> Any:
        """`server.scene.<method>(name, ...)`, the handle remembered in `nodes`."""
        handle = getattr(self.server.scene, method)(name, **kwargs)
        self.nodes[name] = handle
        return handle

    def toggle(self, label: str, handles: Callable[[], Iterable[Any]], value: bool = True) -> Any:
        """A checkbox in the layers folder that shows or hides `handles()`."""
        with self.layers:
            box = self.server.gui.add_checkbox(label, value)

        def apply(_: Any) -> None:
            for handle in handles():
                handle.visible = box.value

        box.on_update(apply)
        apply(None)
        self.toggles[label] = box
        return box

    def reset_frames(self) -> None:
        """Fits the slider to `num_frames` and draws frame 0."""
        self.frame.max = max(self.num_frames - 1, 1)
        if self.frame.value != 0:
            self.frame.value = 0  # redraws through the slider's callback
        else:
            self.show(0)

    def show(self, t: int) -> None:
        """Draws frame `t` (clamped to the motion), all node updates applied at once."""
        with self._lock, self.server.atomic():
            self.draw(clamp_frame(int(t), self.num_frames))

    def look_at(self, centre: np.ndarray, size: float) -> None:
        """The initial camera: in front of `centre` and a little above, far enough back that
        `size` fills most of the view (viser's default vertical field of view is 75 degrees).
        The control panel covers the right of the page, so the scene is shifted left."""
        target = centre + 0.25 * size * self.right
        camera = self.server.initial_camera
        camera.look_at = tuple(float(c) for c in target)
        camera.position = tuple(
            float(c) for c in target + 0.9 * size * (self.towards + 0.3 * self.up)
        )

    def _play(self) -> None:
        while not self._stop.wait(1.0 / self.fps.value):
            if self.playing.value and self.num_frames > 1:
                self.frame.value = (self.frame.value + 1) % self.num_frames

    def record(self, path: str | Path, progress: bool = True) -> Path:
        """Writes every frame, at the speed set, as a viser recording: `.html` a standalone
        page (viser's static client with the recording inside), any other name a `.viser` file
        for the static client's `?playbackPath=`. The GUI is not part of a recording."""
        from tqdm import tqdm

        from nmjax import atomic

        path = Path(path)
        serializer = self.server.get_scene_serializer()
        for t in tqdm(range(self.num_frames), desc="record", unit="frame", disable=not progress):
            self.show(t)
            serializer.insert_sleep(1.0 / self.fps.value)
        data = serializer.as_html().encode() if path.suffix == ".html" else serializer.serialize()
        with atomic.writer(path, "wb") as f:
            f.write(data)
        return path

    def url(self) -> str:
        host = self.server.get_host()
        host = "localhost" if host in ("0.0.0.0", "::", "") else host
        return f"http://{host}:{self.server.get_port()}"

    def stop(self) -> None:
        """Stops playback and the server with its threads."""
        self._stop.set()
        self._player.join()
        self.server.stop()


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
        self.affinity = None
        if data.influence is not None:
            self.affinity_pairs, strength = affinity_pairs(data.influence)
            count = len(self.affinity_pairs)
            cylinder = _unit_cylinder()
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
                from nmjax.data.voxelize import voxel_points, voxelize

                self.voxels.points = voxel_points(voxelize(self.points[t], self.data.grid))
            else:
                self.body.points = self.points[t]
        if self.truth is not None and self.joints is not None:
            self.truth.show(self.joints[t])
        if self.affinity is not None:
            mu = keypoints[:, :3]
            centres, wxyzs, lengths = cylinder_transforms(
                mu[self.affinity_pairs[:, 0]], mu[self.affinity_pairs[:, 1]]
            )
            width = np.full(len(lengths), 0.15 * KEYPOINT_RADIUS)
            self.affinity.batched_positions = centres
            self.affinity.batched_wxyzs = wxyzs
            self.affinity.batched_scales = np.stack([width, width, lengths], axis=1)


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


class GltfViewer(Viewer):
    """A glTF file of `nmjax export`: its skeleton (keypoint colours by the k of `joint_<k>`)
    and its skinned mesh, at every key of its animation; playback at the file's frame rate."""

    kind = "glTF file"

    def __init__(self, server: Any, path: Path, data: Any, up_axis: int):
        super().__init__(server, str(path), up_axis)
        self.data = data
        cloud = data.positions if data.vertices is None else data.vertices
        lo, hi = cloud.reshape(-1, 3).min(axis=0), cloud.reshape(-1, 3).max(axis=0)
        centre, extent = (lo + hi) / 2.0, max(float(np.max(hi - lo)), 1e-6)
        self.mesh = None
        if data.vertices is not None:
            self.mesh = self.add(
                "add_mesh_simple",
                "/gltf/mesh",
                vertices=data.vertices[0].astype(np.float32),
                faces=data.faces,
                color=MESH_COLOR,
                opacity=0.75,
                side="double",
            )
        indices = [_keypoint_index(name, j) for j, name in enumerate(data.names)]
        colors = keypoint_colors(max(indices) + 1)[indices]
        self.pose = Pose(self, "/gltf", data.parents, 0, colors=colors, radius=0.02 * extent)
        self.toggle("mesh", lambda: [] if self.mesh is None else [self.mesh])
        self.toggle("skeleton", lambda: self.pose.handles)
        if len(data.times) > 1:
            rate = 1.0 / float(np.median(np.diff(data.times)))
            self.fps.value = int(np.clip(round(rate), self.fps.min, self.fps.max))
        self.look_at(centre, 1.6 * extent)
        self.reset_frames()

    @property
    def num_frames(self) -> int:
        return len(self.data.times)

    def draw(self, t: int) -> None:
        if self.mesh is not None:
            self.mesh.vertices = self.data.vertices[t].astype(np.float32)
        self.pose.show(self.data.positions[t])


def _keypoint_index(name: str, default: int) -> int:
    """k of a joint named `joint_<k>`; `default` for any other name."""
    prefix, _, number = name.rpartition("_")
    return int(number) if prefix == "joint" and number.isdigit() else default


def _unit_cylinder():
    """A trimesh cylinder of radius 1 and height 1 along z, centred at the origin."""
    import trimesh

    return trimesh.creation.cylinder(radius=1.0, height=1.0, sections=8)


# --- starting a view ----------------------------------------------------------------------------


def pick_sequence(names: Iterable[str], seq: str | None, where: str) -> str:
    """`seq`, or the first name in sorted order when it is None.

    Raises:
      ValueError: `seq` is not among `names` (the message lists some that are).
    """
    names = sorted(names)
    if seq is None:
        return names[0]
    if seq not in names:
        shown = ", ".join(names[:8]) + (f", ... ({len(names)} in all)" if len(names) > 8 else "")
        raise ValueError(f"--seq {seq!r} is not a sequence of {where}; available: {shown}")
    return seq


def check_port(host: str, port: int) -> None:
    """Refuses a `host`:`port` that cannot be listened on (taken, or not this machine's).

    viser itself would move on to the next free port; a view must be where the user (and an
    SSH port forward) expects it.

    Raises:
      OSError: one line naming the port or host and the fix.
    """
    import errno

    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
        with socket.socket(family, kind, proto) as probe:
            # As the server binds: a port left in TIME_WAIT is free, one with a listener is not.
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            probe.bind(address)
    except OSError as err:
        if err.errno == errno.EADDRINUSE:
            raise OSError(
                f"--port {port} is in use on {host}; pick another with --port N"
            ) from None
        raise OSError(
            f"cannot listen on --host {host} --port {port} ({err.strerror or err}); give an "
            "address of this machine (127.0.0.1, or 0.0.0.0 for every interface)"
        ) from None


def start_server(host: str, port: int) -> Any:
    """A viser server on exactly `host`:`port` (0: any free port)."""
    viser = import_viser()
    check_port(host, port)
    server = viser.ViserServer(host=host, port=port, label="nmjax", verbose=False)
    if port and server.get_port() != port:  # taken between the check and the bind
        server.stop()
        raise OSError(f"--port {port} is in use on {host}; pick another with --port N")
    return server


def open_view(
    folder: str | Path,
    *,
    split: str = "test",
    seq: str | None = None,
    host: str = "127.0.0.1",
    port: int = 8080,
    up: str | None = None,
    cond: int = 5,
    gen: int = 25,
    samples: int = 3,
    gap: int = 10,
    trajectories: int = 16,
    seed: int = 0,
) -> Viewer:
    """Reads `folder` and starts a viewer of it on `host`:`port`; `stop()` ends it.

    Everything is read and checked before the port is taken. `up` ("x", "y" or "z") overrides
    the up axis of the run's data (z for a retarget output, y for a glTF file); the phase-2
    options are those of
    `nmjax generate` and `nmjax interpolate`.

    Raises:
      ImportError: viser is not installed (the message names the extra).
      FileNotFoundError, ValueError, OSError: a missing or unfinished folder, an unknown
        sequence, a port in use; one line each.
    """
    from nmjax import runs, tasks

    import_viser()
    folder = Path(folder)
    kind = folder_kind(folder)
    up_axis = None if up is None else UP_AXES.index(up)
    if kind == "gltf":
        from nmjax.export import gltf

        if seq is not None:
            raise ValueError(f"--seq does not apply to {folder}: a glTF file is one motion")
        data = gltf.read(folder)
        server = start_server(host, port)
        try:  # glTF is +Y up
            return GltfViewer(server, folder, data, 1 if up_axis is None else up_axis)
        except BaseException:
            server.stop()
            raise
    if kind == "retarget":
        if seq is not None:
            raise ValueError(f"--seq does not apply to {folder}: a retarget output is one motion")
        data = tasks.read_retarget(folder)
    else:
        data = read_phase1(folder, split) if kind == "skel" else read_phase2(folder, split)
        if up_axis is not None:
            data = dataclasses.replace(data, up_axis=up_axis)
        source = data.run if kind == "skel" else data.skel_run
        seq = pick_sequence(data.keypoints, seq, str(runs.keypoints_file(source, split)))
    server = start_server(host, port)
    try:
        if kind == "skel":
            return Phase1Viewer(server, data, seq)
        if kind == "dyn":
            return Phase2Viewer(
                server,
                data,
                seq,
                cond=cond,
                gen=gen,
                samples=samples,
                gap=gap,
                trajectories=trajectories,
                seed=seed,
            )
        return RetargetViewer(server, folder, data, 2 if up_axis is None else up_axis)
    except BaseException:
        server.stop()
        raise
