"""The viewer every view shares: a viser server with a frame slider, play / pause at a speed in
frames per second, one toggle per layer, and the recording of every frame (`Viewer.record`);
`Pose`, one keypoint set in the scene. Subclasses per run kind say what they show."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

from nmjax.view.draw import (
    BONE_COLOR,
    KEYPOINT_RADIUS,
    ROOT_COLOR,
    bone_pairs,
    clamp_frame,
    keypoint_colors,
    keypoint_radii,
    view_axes,
)


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
