"""A `Rig` as glTF 2.0 (.glb, or .gltf with its buffer embedded), through pygltflib; and the
reader `nmjax view` opens such a file with.

The file: one node per joint (named `joint_<k>`, children as in the tree, its TRS the rest
pose), a skin over them with inverse bind matrices, an animation with a rotation and a
translation channel per joint (LINEAR samplers keyed at frame / fps, see `nmjax.export.rig` for
why every joint has a translation), and, with a mesh, a skinned mesh (POSITION, JOINTS_0,
WEIGHTS_0: the four largest weights per vertex) on a node of its own beside the skeleton; a
rig whose surface has no faces (a point cloud, `Rig.faces` None) is skinned the same way as a
POINTS primitive.
"""

from __future__ import annotations

import base64
import dataclasses
from pathlib import Path

import numpy as np
import pygltflib

from nmjax import atomic
from nmjax.export.rig import (
    Rig,
    compose,
    inverse_bind_matrices,
    local_transforms,
    quaternions_xyzw,
    top_influences,
)

GENERATOR = "nmjax export"
MESH_COLOR = (0.78, 0.71, 0.59, 1.0)
_DATA_URI = "data:application/octet-stream;base64,"
# numpy dtype of every glTF component type the writer uses, and the reader's of the same.
_COMPONENTS = {
    pygltflib.FLOAT: np.float32,
    pygltflib.UNSIGNED_INT: np.uint32,
    pygltflib.UNSIGNED_SHORT: np.uint16,
    pygltflib.UNSIGNED_BYTE: np.uint8,
}
_WIDTH = {pygltflib.SCALAR: 1, pygltflib.VEC3: 3, pygltflib.VEC4: 4, pygltflib.MAT4: 16}


class _Buffer:
    """The file's one binary buffer, grown one accessor (and buffer view) at a time."""

    def __init__(self, gltf: pygltflib.GLTF2):
        self.gltf = gltf
        self.data = bytearray()

    def add(
        self,
        array: np.ndarray,
        kind: str,
        component: int,
        target: int | None = None,
        bounds: bool = False,
    ) -> int:
        """Appends `array` (N, width) as an accessor of `kind`; returns the accessor's index.

        Every view starts 4-byte aligned, as glTF requires of its accessors' components.
        `bounds` stores min / max (required for POSITION and for animation inputs).
        """
        array = np.ascontiguousarray(array, dtype=_COMPONENTS[component])
        self.data += b"\0" * (-len(self.data) % 4)
        self.gltf.bufferViews.append(
            pygltflib.BufferView(
                buffer=0, byteOffset=len(self.data), byteLength=array.nbytes, target=target
            )
        )
        self.data += array.tobytes()
        flat = array.reshape(len(array), -1)
        accessor = pygltflib.Accessor(
            bufferView=len(self.gltf.bufferViews) - 1,
            componentType=component,
            count=len(array),
            type=kind,
        )
        if bounds:
            accessor.min = flat.min(axis=0).tolist()
            accessor.max = flat.max(axis=0).tolist()
        self.gltf.accessors.append(accessor)
        return len(self.gltf.accessors) - 1


def build(rig: Rig) -> tuple[pygltflib.GLTF2, bytes]:
    """The glTF document of `rig` and its binary buffer (not yet attached to a file)."""
    gltf = pygltflib.GLTF2(asset=pygltflib.Asset(version="2.0", generator=GENERATOR))
    buffer = _Buffer(gltf)
    num = len(rig.joints)
    rest_rot, rest_trans = local_transforms(
        rig.rest_positions[None], rig.rest_rotations[None], rig.parents
    )
    rest_quat = quaternions_xyzw(rest_rot)[0]
    for j, name in enumerate(rig.names):
        gltf.nodes.append(
            pygltflib.Node(
                name=name,
                children=rig.children(j) or None,
                translation=rest_trans[0, j].tolist(),
                rotation=rest_quat[j].tolist(),
            )
        )
    ibm = inverse_bind_matrices(rig.rest_positions, rig.rest_rotations)
    # glTF matrices are column-major: write each transposed.
    ibm_accessor = buffer.add(
        np.swapaxes(ibm, -1, -2).reshape(num, 16), pygltflib.MAT4, pygltflib.FLOAT
    )
    gltf.skins.append(
        pygltflib.Skin(
            name="skeleton", joints=list(range(num)), skeleton=0, inverseBindMatrices=ibm_accessor
        )
    )
    scene_nodes = [0]
    if rig.vertices is not None:
        scene_nodes.append(_add_mesh(gltf, buffer, rig))
    _add_animation(gltf, buffer, rig)
    gltf.scenes.append(pygltflib.Scene(name=rig.name, nodes=scene_nodes))
    gltf.scene = 0
    gltf.buffers.append(pygltflib.Buffer(byteLength=len(buffer.data)))
    return gltf, bytes(buffer.data)


def _add_mesh(gltf: pygltflib.GLTF2, buffer: _Buffer, rig: Rig) -> int:
    """The skinned mesh and its node (returned); glTF ignores a skinned mesh node's own
    transform, so it sits at the scene's top level. Without faces the vertices are one POINTS
    primitive (no indices), skinned alike."""
    index, weights = top_influences(rig.weights)
    joint_type = pygltflib.UNSIGNED_BYTE if len(rig.joints) <= 256 else pygltflib.UNSIGNED_SHORT
    array_buffer = pygltflib.ARRAY_BUFFER
    attributes = pygltflib.Attributes(
        POSITION=buffer.add(
            rig.vertices, pygltflib.VEC3, pygltflib.FLOAT, array_buffer, bounds=True
        ),
        JOINTS_0=buffer.add(index, pygltflib.VEC4, joint_type, array_buffer),
        WEIGHTS_0=buffer.add(weights, pygltflib.VEC4, pygltflib.FLOAT, array_buffer),
    )
    points = rig.faces is None or len(rig.faces) == 0
    indices = None
    if not points:
        indices = buffer.add(
            np.asarray(rig.faces).reshape(-1),
            pygltflib.SCALAR,
            pygltflib.UNSIGNED_INT,
            pygltflib.ELEMENT_ARRAY_BUFFER,
        )
    gltf.materials.append(
        pygltflib.Material(
            name="skin",
            doubleSided=True,
            pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
                baseColorFactor=list(MESH_COLOR), metallicFactor=0.0, roughnessFactor=0.8
            ),
        )
    )
    mode = pygltflib.POINTS if points else pygltflib.TRIANGLES
    primitive = pygltflib.Primitive(attributes=attributes, indices=indices, material=0, mode=mode)
    name = "points" if points else "mesh"
    gltf.meshes.append(pygltflib.Mesh(name=name, primitives=[primitive]))
    gltf.nodes.append(pygltflib.Node(name=name, mesh=0, skin=0))
    return len(gltf.nodes) - 1


def _add_animation(gltf: pygltflib.GLTF2, buffer: _Buffer, rig: Rig) -> None:
    """One rotation and one translation channel per joint, keyed at every frame."""
    local_rot, local_trans = local_transforms(rig.positions, rig.rotations, rig.parents)
    quat = quaternions_xyzw(local_rot)  # (T, J, 4)
    times = np.arange(rig.num_frames, dtype=np.float64) / rig.frame_rate
    keys = buffer.add(times, pygltflib.SCALAR, pygltflib.FLOAT, bounds=True)
    animation = pygltflib.Animation(name=rig.name)
    for j in range(len(rig.joints)):
        for path, values, kind in (
            ("rotation", quat[:, j], pygltflib.VEC4),
            ("translation", local_trans[:, j], pygltflib.VEC3),
        ):
            animation.samplers.append(
                pygltflib.AnimationSampler(
                    input=keys,
                    output=buffer.add(values, kind, pygltflib.FLOAT),
                    interpolation=pygltflib.ANIM_LINEAR,
                )
            )
            animation.channels.append(
                pygltflib.AnimationChannel(
                    sampler=len(animation.samplers) - 1,
                    target=pygltflib.AnimationChannelTarget(node=j, path=path),
                )
            )
    gltf.animations.append(animation)


def write(rig: Rig, path: str | Path) -> Path:
    """Writes `rig` as .glb (binary) or .gltf (JSON, the buffer embedded as a data URI), by
    the suffix of `path`, atomically."""
    path = Path(path)
    gltf, blob = build(rig)
    if path.suffix.lower() == ".glb":
        gltf.set_binary_blob(blob)
        data = b"".join(gltf.save_to_bytes())
    else:
        gltf.buffers[0].uri = _DATA_URI + base64.b64encode(blob).decode("ascii")
        data = gltf.gltf_to_json().encode("utf-8")
    with atomic.writer(path, "wb") as f:
        f.write(data)
    return path


# --- reading a file back (`nmjax view FILE.glb`) ------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Animated:
    """A glTF file's skinned skeleton sampled at its keyframes.

    Attributes:
      names: (J,) joint node names; parents: (J,) parent indices into them (root its own).
      times: (T,) key times in seconds.
      positions: (T, J, 3) joint world positions; rotations: (T, J, 3, 3) world rotations.
      vertices: (T, V, 3) the skinned mesh (or points) at every key, or None; faces: (F, 3),
        or None for points or no mesh.
    """

    names: list[str]
    parents: np.ndarray
    times: np.ndarray
    positions: np.ndarray
    rotations: np.ndarray
    vertices: np.ndarray | None
    faces: np.ndarray | None


def accessor_array(gltf: pygltflib.GLTF2, blob: bytes, index: int) -> np.ndarray:
    """Accessor `index` as a (count, width) array (tightly packed views, as `write` makes)."""
    accessor = gltf.accessors[index]
    view = gltf.bufferViews[accessor.bufferView]
    dtype = np.dtype(_COMPONENTS[accessor.componentType])
    width = _WIDTH[accessor.type]
    start = (view.byteOffset or 0) + (accessor.byteOffset or 0)
    flat = np.frombuffer(blob, dtype, accessor.count * width, start)
    return flat.reshape(accessor.count, width)


def load(path: str | Path) -> tuple[pygltflib.GLTF2, bytes]:
    """(document, binary buffer) of a .glb or a .gltf whose buffer is embedded.

    Raises:
      ValueError: not a glTF file pygltflib reads, or a .gltf whose buffer is a separate file.
    """
    path = Path(path)
    try:
        if path.suffix.lower() == ".glb":
            gltf = pygltflib.GLTF2.load_binary(path)
            blob = gltf.binary_blob()
        else:
            gltf = pygltflib.GLTF2.load_json(path)
            uri = (gltf.buffers[0].uri or "") if gltf.buffers else ""
            if not uri.startswith("data:"):
                raise ValueError("its buffer is not embedded")
            blob = base64.b64decode(uri.split(",", 1)[1])
    except Exception as err:  # pygltflib raises many types for damaged files
        raise ValueError(
            f"cannot read {path} as glTF ({' '.join(str(err).split())}); give a file written "
            "by `nmjax export`"
        ) from err
    if gltf is None or blob is None:
        raise ValueError(f"cannot read {path} as glTF; give a file written by `nmjax export`")
    return gltf, blob


def read(path: str | Path) -> Animated:
    """The skeleton of a file's first skin, posed at every key of its first animation by glTF's
    rules (node TRS composed down the hierarchy), and its skinned mesh posed the same way.

    Raises:
      ValueError: the file has no skin or no animation, or joints outside one tree.
    """
    from scipy.spatial.transform import Rotation

    gltf, blob = load(path)
    if not gltf.skins or not gltf.animations:
        raise ValueError(f"{path} has no skin or no animation; give a file of `nmjax export`")
    skin = gltf.skins[0]
    nodes = list(skin.joints)
    slot = {n: j for j, n in enumerate(nodes)}
    parents = np.arange(len(nodes))
    for j, n in enumerate(nodes):
        for child in gltf.nodes[n].children or []:
            if child in slot:
                parents[slot[child]] = j
    if np.count_nonzero(parents == np.arange(len(nodes))) != 1 or parents[0] != 0:
        raise ValueError(f"{path}: the skin's joints are not one tree with the first as root")
    animation = gltf.animations[0]
    times = accessor_array(gltf, blob, animation.samplers[0].input)[:, 0].astype(np.float64)
    num = len(times)
    rest = [gltf.nodes[n] for n in nodes]
    quat = np.array([r.rotation or [0, 0, 0, 1] for r in rest], np.float64)
    local_rot = np.broadcast_to(Rotation.from_quat(quat).as_matrix(), (num, len(nodes), 3, 3))
    local_trans = np.broadcast_to(
        np.array([r.translation or [0, 0, 0] for r in rest], np.float64), (num, len(nodes), 3)
    )
    local_rot, local_trans = local_rot.copy(), local_trans.copy()
    for channel in animation.channels:
        j = slot.get(channel.target.node)
        if j is None or channel.target.path not in ("rotation", "translation"):
            continue
        sampler = animation.samplers[channel.sampler]
        keys = accessor_array(gltf, blob, sampler.input)[:, 0].astype(np.float64)
        values = accessor_array(gltf, blob, sampler.output).astype(np.float64)
        sampled = np.stack([np.interp(times, keys, v) for v in values.T], axis=-1)
        if channel.target.path == "rotation":
            local_rot[:, j] = Rotation.from_quat(sampled).as_matrix()
        else:
            local_trans[:, j] = sampled
    positions, rotations = compose(local_rot, local_trans, parents)
    vertices = faces = None
    mesh_node = next((n for n in gltf.nodes if n.mesh is not None and n.skin == 0), None)
    if mesh_node is not None:
        primitive = gltf.meshes[mesh_node.mesh].primitives[0]
        rest_vertices = accessor_array(gltf, blob, primitive.attributes.POSITION)
        joints = accessor_array(gltf, blob, primitive.attributes.JOINTS_0).astype(np.int64)
        weights = accessor_array(gltf, blob, primitive.attributes.WEIGHTS_0).astype(np.float64)
        ibm = accessor_array(gltf, blob, skin.inverseBindMatrices).reshape(-1, 4, 4)
        vertices = skin_vertices(rest_vertices, joints, weights, positions, rotations, ibm)
        if primitive.indices is not None:  # a POINTS primitive has none
            faces = accessor_array(gltf, blob, primitive.indices).reshape(-1, 3).astype(np.int64)
    names = [gltf.nodes[n].name or f"node_{n}" for n in nodes]
    return Animated(names, parents, times, positions, rotations, vertices, faces)


def skin_vertices(
    vertices: np.ndarray,
    joints: np.ndarray,
    weights: np.ndarray,
    positions: np.ndarray,
    rotations: np.ndarray,
    inverse_bind: np.ndarray,
) -> np.ndarray:
    """glTF skinning: v_t = sum_i w_i (joint matrix_t[j_i] @ inverse bind[j_i]) v.

    Args:
      vertices: (V, 3); joints, weights: (V, 4); positions (T, J, 3) and rotations (T, J, 3, 3)
      the joints' world transforms; inverse_bind: (J, 4, 4) as stored (column-major, so each is
      transposed here).

    Returns:
      (T, V, 3).
    """
    ibm = np.swapaxes(inverse_bind, -1, -2).astype(np.float64)
    world = np.zeros((*rotations.shape[:-2], 4, 4))
    world[..., :3, :3], world[..., :3, 3], world[..., 3, 3] = rotations, positions, 1.0
    skin = world @ ibm  # (T, J, 4, 4)
    blended = sum(weights[:, n, None, None] * skin[:, joints[:, n]] for n in range(joints.shape[1]))
    homogeneous = np.concatenate([vertices, np.ones((len(vertices), 1))], axis=1)
    return np.einsum("tvij,vj->tvi", blended, homogeneous)[..., :3]
