"""The view of a glTF file written by `nmjax export` (.glb / .gltf): its skeleton and skinned mesh
posed at every key of its animation by glTF's own rules (`nmjax.export.gltf.read`), so that a
file can be checked before it is sent on."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from nmjax.view.draw import (
    MESH_COLOR,
    keypoint_colors,
)
from nmjax.view.viewer import Pose, Viewer


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
        if data.vertices is not None and data.faces is not None:
            self.mesh = self.add(
                "add_mesh_simple",
                "/gltf/mesh",
                vertices=data.vertices[0].astype(np.float32),
                faces=data.faces,
                color=MESH_COLOR,
                opacity=0.75,
                side="double",
            )
        elif data.vertices is not None:  # a skinned point cloud (glTF POINTS)
            self.mesh = self.add(
                "add_point_cloud",
                "/gltf/points",
                points=data.vertices[0].astype(np.float32),
                colors=MESH_COLOR,
                point_size=0.005 * extent,
                point_shape="circle",
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
        if self.mesh is not None and self.data.faces is not None:
            self.mesh.vertices = self.data.vertices[t].astype(np.float32)
        elif self.mesh is not None:
            self.mesh.points = self.data.vertices[t].astype(np.float32)
        self.pose.show(self.data.positions[t])


def _keypoint_index(name: str, default: int) -> int:
    """k of a joint named `joint_<k>`; `default` for any other name."""
    prefix, _, number = name.rpartition("_")
    return int(number) if prefix == "joint" and number.isdigit() else default
