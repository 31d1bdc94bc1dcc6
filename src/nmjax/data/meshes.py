"""Mesh and point files as users hand them to nmjax: mesh frames of `nmjax prepare-data`
(.obj / .ply / .off) with their joints.npy, the target mesh of `nmjax retarget` (anything trimesh
reads), point-sequence .npy files of `--source-file`; and area-uniform sampling of a surface.

trimesh is imported where a mesh is read, which keeps `nmjax --help` fast. Every reader raises
FileNotFoundError or ValueError naming the file.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

MESH_SUFFIXES = (".obj", ".ply", ".off")  # the mesh frames `nmjax prepare-data` reads


def read_mesh(path: str | os.PathLike, fix: str = ""):
    """One mesh file as a trimesh.Trimesh (a scene concatenated), vertices and faces as stored.

    Raises:
      ValueError naming the file: trimesh cannot read it (`fix`, when given, says what to do).
    """
    import trimesh  # lazy: keeps `nmjax --help` fast

    try:
        return trimesh.load(path, force="mesh", process=False)
    except Exception as err:  # trimesh raises many types for broken files
        advice = f"; {fix}" if fix else ""
        raise ValueError(
            f"cannot read the mesh {path} ({type(err).__name__}: {err}){advice}"
        ) from err


def sample_surface(
    vertices: np.ndarray, faces: np.ndarray, points: int, seed: int, where: str
) -> np.ndarray:
    """(points, 3) float32 points area-uniform on the triangles `faces` of `vertices` (V, 3): one
    mesh as given, sampled by trimesh with `seed` (the synthetic bodies, rigid links carried
    through a motion, are sampled by `nmjax.data.synthetic.sample_body_surface`).

    Raises:
      ValueError naming `where`: no face of positive area, or NaN / inf vertices.
    """
    import trimesh  # lazy: keeps `nmjax --help` fast

    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    if len(mesh.faces) == 0 or not mesh.area > 0:
        raise ValueError(f"{where}: mesh has no surface (faces: {len(mesh.faces)}) to sample from")
    sampled, _ = trimesh.sample.sample_surface(mesh, points, seed=seed)
    sampled = np.asarray(sampled, dtype=np.float32)
    if not np.isfinite(sampled).all():
        raise ValueError(f"{where}: mesh vertices contain NaN or inf")
    return sampled


def load_mesh(path: str | os.PathLike):
    """Reads a target mesh (.obj, .ply, .off, .stl, ... anything trimesh reads) and checks it.

    Watertight or not, one mesh or a scene (concatenated). Raises:
      FileNotFoundError: no such file.
      ValueError naming the file: unreadable, no vertices or faces, NaN / inf vertices.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"target mesh {path} does not exist (--target)")
    mesh = read_mesh(path, "give an .obj, .ply, .off or .stl mesh with vertices and faces")
    vertices = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), np.float64)
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))))
    if vertices.ndim != 2 or len(vertices) == 0:
        raise ValueError(f"target mesh {path} has no vertices; give a non-empty mesh")
    if not np.all(np.isfinite(vertices)):
        bad = int(np.sum(~np.all(np.isfinite(vertices), axis=1)))
        raise ValueError(
            f"target mesh {path} has {bad} vertices with NaN or inf coordinates; repair the file"
        )
    if faces.ndim != 2 or len(faces) == 0:
        raise ValueError(
            f"target mesh {path} has no faces (a point cloud?); retargeting samples points on the "
            "surface and needs a triangle mesh"
        )
    if float(np.sum(mesh.area_faces)) <= 0.0:
        raise ValueError(f"target mesh {path} has zero surface area; give a non-degenerate mesh")
    return mesh


def read_joints(path: Path, num_frames: int) -> np.ndarray:
    """The joints.npy of a mesh-frame folder (`nmjax prepare-data`): (T, J, 3) float32, T the
    folder's mesh frames; ValueError naming the file for another shape or NaN / inf."""
    joints = np.load(path, allow_pickle=False)
    if joints.ndim != 3 or joints.shape[-1] != 3 or joints.shape[0] != num_frames:
        raise ValueError(
            f"{path}: joints must have shape (T, J, 3) with T = {num_frames} mesh frames, "
            f"got {joints.shape}"
        )
    if not np.isfinite(joints).all():
        raise ValueError(f"{path}: joints contain NaN or inf")
    return joints.astype(np.float32)


def load_point_sequence(path: str | os.PathLike) -> np.ndarray:
    """Reads a point-sequence file: a NumPy .npy of shape (T, N, >= 3), xyz first (the format
    of the authors' data/demo/source/*.npy; further columns such as normals are dropped).

    Returns:
      (T, N, 3) float32.

    Raises:
      FileNotFoundError: no such file.
      ValueError naming the file: not a .npy array, another shape, NaN / inf coordinates.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"point-sequence file {path} does not exist (--source-file)")
    try:
        points = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as err:
        raise ValueError(
            f"cannot read {path} as a NumPy .npy array ({' '.join(str(err).split())}); give a "
            "(T, N, 3) point sequence saved with numpy.save"
        ) from err
    if points.ndim != 3 or points.shape[-1] < 3 or 0 in points.shape:
        raise ValueError(
            f"{path} holds an array of shape {points.shape}; a point sequence is (T frames, N "
            "points, >= 3 coordinates)"
        )
    points = np.asarray(points[..., :3], np.float32)
    if not np.all(np.isfinite(points)):
        raise ValueError(f"{path} has NaN or inf coordinates; repair the file")
    return points
