"""Mesh and point files as users hand them to nmjax: the frames of `nmjax prepare-data` (meshes
.obj / .ply / .off, or point clouds: vertices-only .ply / .obj / .off, .xyz / .txt, .npy) with
their joints.npy, the target mesh of `nmjax retarget` (anything trimesh reads), point-sequence
.npy files of `--source-file`; and area-uniform sampling of a surface.

trimesh is imported where a mesh is read, which keeps `nmjax --help` fast. Every reader raises
FileNotFoundError or ValueError naming the file; `require_finite` names the first NaN / inf
vertex (and frame).
"""

from __future__ import annotations

import io
import os
import warnings
import zipfile
from pathlib import Path

import numpy as np

MESH_SUFFIXES = (".obj", ".ply", ".off")  # mesh frames (or vertices-only point clouds)
POINT_SUFFIXES = (".xyz", ".txt", ".npy")  # point-cloud frames: x y z lines, or an (N, 3) array
FRAME_SUFFIXES = MESH_SUFFIXES + POINT_SUFFIXES  # the frames `nmjax prepare-data` reads


def read_mesh(path: str | os.PathLike, fix: str = ""):
    """One mesh file as a trimesh.Trimesh (a scene concatenated), vertices and faces as stored.

    Raises:
      ValueError naming the file: trimesh cannot read it (`fix`, when given, says what to do).
    """
    import trimesh  # lazy: keeps `nmjax --help` fast

    try:
        return trimesh.load(path, force="mesh", process=False)
    except Exception as err:  # trimesh raises many types for broken files
        raise _unreadable(path, err, fix) from err


def _unreadable(path: str | os.PathLike, err: Exception, fix: str) -> ValueError:
    advice = f"; {fix}" if fix else ""
    return ValueError(f"cannot read the mesh {path} ({type(err).__name__}: {err}){advice}")


def read_frame(path: str | os.PathLike, fix: str = "") -> tuple[np.ndarray, np.ndarray]:
    """One frame file as (vertices (V, 3) float64, faces (F, 3) int64), F = 0 for a point cloud.

    .obj / .ply / .off (and whatever else trimesh reads): a mesh, or its vertices alone when the
    file has no faces (a scene: its meshes concatenated, or its points when it has no mesh).
    .xyz / .txt: one point a line, x y z first, separated by spaces or commas ("#" starts a
    comment). .npy: an (N, >= 3) array. Further columns (normals, colours) are dropped.
    NaN / inf are returned as stored (`require_finite` names them).

    Raises:
      ValueError naming the file: unreadable, fewer than three columns, no vertices.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".xyz", ".txt"):
        text = path.read_text(errors="replace").replace(",", " ")
        try:
            with warnings.catch_warnings():  # an empty file: refused below, naming it
                warnings.simplefilter("ignore", UserWarning)
                vertices = np.loadtxt(
                    io.StringIO(text), comments="#", usecols=(0, 1, 2), ndmin=2, dtype=np.float64
                )
        except ValueError as err:
            why = " ".join(str(err).split())
            raise ValueError(f"cannot read {path} as `x y z` point lines ({why})") from err
        faces = np.zeros((0, 3), np.int64)
    elif suffix == ".npy":
        try:
            vertices = np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as err:
            raise ValueError(
                f"cannot read {path} as a NumPy .npy array ({' '.join(str(err).split())}); give "
                "an (N, 3) array of points saved with numpy.save"
            ) from err
        if vertices.ndim != 2 or not np.issubdtype(vertices.dtype, np.number):
            raise ValueError(
                f"{path} holds an array of shape {vertices.shape} and dtype {vertices.dtype}; "
                "a point-cloud frame is (N points, 3) numbers"
            )
        faces = np.zeros((0, 3), np.int64)
    else:
        vertices, faces = _read_trimesh(path, fix)
    if vertices.ndim != 2 or (len(vertices) and vertices.shape[1] < 3):
        raise ValueError(
            f"{path}: points need three columns (x y z), got {vertices.shape[-1]} per point"
        )
    if len(vertices) == 0:
        raise ValueError(f"{path} holds no vertices; give a non-empty mesh or point cloud")
    return np.asarray(vertices[:, :3], np.float64), faces


def _read_trimesh(path: Path, fix: str) -> tuple[np.ndarray, np.ndarray]:
    import trimesh  # lazy: keeps `nmjax --help` fast

    try:
        loaded = trimesh.load(path, process=False)
    except Exception as err:  # trimesh raises many types for broken files
        raise _unreadable(path, err, fix) from err
    if isinstance(loaded, trimesh.Scene):
        parts = loaded.dump()  # its geometry placed by the scene graph
        if any(isinstance(part, trimesh.Trimesh) for part in parts):
            loaded = loaded.to_mesh()
        else:
            clouds = [np.asarray(part.vertices) for part in parts if hasattr(part, "vertices")]
            loaded = trimesh.PointCloud(np.concatenate(clouds) if clouds else np.zeros((0, 3)))
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), np.float64)
    faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), np.int64)
    return vertices.reshape(-1, 3), faces.reshape(-1, 3)


def require_finite(points: np.ndarray, where: str) -> None:
    """Refuses NaN / inf in `points`, (N, 3) or (T, N, 3), naming the first: "`where`: NaN at
    vertex 7" or "`where`: inf at frame 3, vertex 7" (indices counted from 0).

    Raises:
      ValueError naming `where`, the kind (NaN or inf) and where the first one is.
    """
    with np.errstate(over="ignore", invalid="ignore"):  # float64 beyond float32 is inf as well
        bad = ~np.isfinite(np.asarray(points, np.float32)).all(axis=-1)
    if not bad.any():
        return
    at = tuple(int(i) for i in np.argwhere(bad)[0])
    kind = "NaN" if np.isnan(np.asarray(points[at], np.float64)).any() else "inf"
    place = f"vertex {at[0]}" if len(at) == 1 else f"frame {at[0]}, vertex {at[1]}"
    raise ValueError(f"{where}: {kind} at {place} (counting from 0); repair the file")


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

    Watertight or not, one mesh or a scene (concatenated). Returns a trimesh.Trimesh. Raises:
      FileNotFoundError: no such file.
      ValueError naming the file: unreadable, no vertices, NaN / inf vertices, a point cloud (no
        faces), no surface area.
    """
    import trimesh  # lazy: keeps `nmjax --help` fast

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"target mesh {path} does not exist (--target)")
    fix = "give an .obj, .ply, .off or .stl mesh with vertices and faces"
    vertices, faces = read_frame(path, fix)
    if not np.all(np.isfinite(vertices)):
        bad = int(np.sum(~np.all(np.isfinite(vertices), axis=1)))
        raise ValueError(
            f"target mesh {path} has {bad} vertices with NaN or inf coordinates; repair the file"
        )
    if len(faces) == 0:
        raise ValueError(
            f"target mesh {path} has no faces: it is a point cloud ({len(vertices)} points); "
            "retargeting skins a mesh, so --target needs a mesh with faces (triangles): "
            f"{fix.removeprefix('give ')}"
        )
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
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
    require_finite(points[..., :3], str(path))
    return np.asarray(points[..., :3], np.float32)


POINT_ARRAY_SUFFIXES = (".npy", ".npz")  # one (T, N, 3) array per sequence (`nmjax prepare-data`)


def point_array_shape(path: Path) -> tuple[int, ...]:
    """The shape of the one point sequence in an .npy or .npz file (`read_point_array`), from
    its header only: listing a large capture reads no points.

    Raises:
      ValueError naming the file: unreadable, no single array to take, not (T, N, >= 3) numbers.
    """
    fix = "give a (T, N, 3) point sequence saved with numpy.save / numpy.savez"
    try:
        if path.suffix.lower() == ".npy":
            array = np.load(path, mmap_mode="r", allow_pickle=False)
            shape, dtype = array.shape, array.dtype
            del array  # closes the memory map
        else:
            with zipfile.ZipFile(path) as archive, archive.open(npz_member(path)) as member:
                fmt = np.lib.format
                old = fmt.read_magic(member) == (1, 0)
                header = fmt.read_array_header_1_0 if old else fmt.read_array_header_2_0
                shape, _, dtype = header(member)
    except (OSError, EOFError, zipfile.BadZipFile) as err:
        raise ValueError(f"cannot read {path} ({' '.join(str(err).split())}); {fix}") from err
    except ValueError as err:
        if str(path) in str(err):  # npz_member's own message
            raise
        raise ValueError(f"cannot read {path} ({' '.join(str(err).split())}); {fix}") from err
    if len(shape) != 3 or shape[-1] < 3 or 0 in shape or not np.issubdtype(dtype, np.number):
        raise ValueError(
            f"{path} holds an array of shape {shape} and dtype {dtype}; a point sequence is (T "
            "frames, N points, 3) numbers"
        )
    return tuple(shape)


def npz_member(path: Path) -> str:
    """The archive member of an .npz's point sequence: its only array, else "points", else
    "vertices".

    Raises:
      ValueError naming the file and its arrays when none of these is there.
    """
    with zipfile.ZipFile(path) as archive:
        names = [name.removesuffix(".npy") for name in archive.namelist()]
    for pick in names if len(names) == 1 else ["points", "vertices"]:
        if pick in names:
            return f"{pick}.npy"
    raise ValueError(
        f"{path} holds the arrays {names}; give one array, or name the point sequence `points`"
    )


def read_point_array(path: Path, frames: int) -> np.ndarray:
    """The first `frames` frames of the point sequence in an .npy / .npz file: (frames, N, 3)
    float64, xyz first (further columns dropped), checked for NaN / inf.

    Raises:
      ValueError naming the file: as `point_array_shape`, or the first NaN / inf (frame, vertex).
    """
    point_array_shape(path)
    if path.suffix.lower() == ".npy":
        points = np.load(path, mmap_mode="r", allow_pickle=False)[:frames, :, :3]
    else:
        with np.load(path, allow_pickle=False) as archive:
            points = archive[npz_member(path).removesuffix(".npy")][:frames, :, :3]
    points = np.asarray(points, np.float64)
    require_finite(points, str(path))
    return points
