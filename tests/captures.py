"""Captures written by the tests, as a user hands them to `nmjax prepare-data --from RAW` and
`nmjax rig --from RAW`: synthetic arm bodies (`nmjax.data.synthetic`) as point-cloud frames in
every format, as mesh frames, and each bad input `prepare-data` refuses (`bad_capture`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from nmjax.data import synthetic
from nmjax.data.bodies import get_body


def body(frames: int, points: int = 400, seed: int = 0) -> np.ndarray:
    """(frames, points, 3) float32 surface points of a moving synthetic arm."""
    return synthetic.simulate("synth-arm", frames, points=points, rng=seed).vertices


def write_frame(path: Path, points: np.ndarray) -> None:
    """One point-cloud frame in the format its suffix names."""
    if path.suffix == ".ply":
        trimesh.PointCloud(points).export(path)
    elif path.suffix == ".npy":
        np.save(path, points)
    else:  # .xyz / .txt: one `x y z` line a point
        np.savetxt(path, points)


def write_frames(folder: Path, frames: list[np.ndarray], suffix: str) -> list[Path]:
    folder.mkdir(parents=True)
    paths = [folder / f"frame_{t:03d}{suffix}" for t in range(len(frames))]
    for path, points in zip(paths, frames, strict=True):
        write_frame(path, points)
    return paths


def arm_motion(frames: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Joint positions (T, J, 3) and world rotations (T, J, 3, 3) of a moving synthetic arm."""
    body = get_body("synth-arm")
    angles, root = synthetic.sample_motion(body, frames, np.random.default_rng(seed))
    return synthetic.pose(body, angles, root)


def arm_meshes(positions: np.ndarray, rotations: np.ndarray) -> list[trimesh.Trimesh]:
    """The arm's surface at every frame of a motion (`arm_motion`): its link triangles carried
    by their joints, one mesh a frame with the same vertices (three a triangle) in every frame."""
    triangles, owner = synthetic.body_triangles(get_body("synth-arm"))
    faces = np.arange(3 * len(triangles)).reshape(-1, 3)
    meshes = []
    for pos, rot in zip(positions, rotations, strict=True):
        world = np.einsum("fij,fcj->fci", rot[owner], triangles) + pos[owner, None]
        meshes.append(trimesh.Trimesh(world.reshape(-1, 3), faces, process=False))
    return meshes


def arm_points(positions: np.ndarray, rotations: np.ndarray, points: int, seed: int = 0):
    """(T, points, 3) surface points of the arm at every frame of a motion (`arm_motion`)."""
    body = get_body("synth-arm")
    rng = np.random.default_rng(seed)
    return synthetic.sample_body_surface(body, positions, rotations, points, rng)


def write_meshes(folder: Path, meshes: list[trimesh.Trimesh], suffix: str = ".obj") -> list[Path]:
    folder.mkdir(parents=True)
    paths = [folder / f"frame_{t:03d}{suffix}" for t in range(len(meshes))]
    for path, mesh in zip(paths, meshes, strict=True):
        mesh.export(path)
    return paths


def _nan_at(points: np.ndarray, index: int, value: float = np.nan) -> np.ndarray:
    points = points.copy()
    points[index, 1] = value
    return points


def bad_capture(raw: Path, case: str) -> None:
    """Writes the capture of one bad-input `case` into `raw`."""
    frames = list(body(4, 300))
    if case in ("nan-ply", "inf-xyz", "nan-npy-frame"):
        suffix = {"nan-ply": ".ply", "inf-xyz": ".xyz", "nan-npy-frame": ".npy"}[case]
        value = np.inf if case == "inf-xyz" else np.nan
        frames[3] = _nan_at(frames[3], 7, value)
        write_frames(raw / "wave", frames, suffix)
    elif case == "nan-obj":
        (raw / "wave").mkdir(parents=True)
        for t in range(3):
            box = trimesh.creation.box()
            if t == 2:
                box.vertices[5] = np.nan
            box.export(raw / "wave" / f"frame_{t:03d}.obj")
    elif case == "nan-array":
        raw.mkdir()
        sequence = np.stack(frames)
        sequence[2, 5, 0] = np.nan
        np.savez(raw / "wave.npz", sequence)
    elif case == "junk-xyz":
        write_frames(raw / "wave", frames, ".xyz")
        (raw / "wave" / "frame_002.xyz").write_text("these are not numbers\n")
    elif case == "two-columns":
        write_frames(raw / "wave", [x[:, :2] for x in frames], ".txt")
    elif case == "empty-ply":
        write_frames(raw / "wave", frames, ".ply")
        (raw / "wave" / "frame_001.ply").write_text(
            "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
            "property float z\nend_header\n"
        )
    elif case == "junk-ply":
        write_frames(raw / "wave", frames, ".ply")
        (raw / "wave" / "frame_001.ply").write_bytes(b"not a ply file\x00\xff")
    elif case == "mixed":
        write_frames(raw / "wave", frames, ".ply")
        trimesh.creation.box().export(raw / "wave" / "frame_002.ply")
    elif case == "two-arrays":
        raw.mkdir()
        np.savez(raw / "wave.npz", a=np.stack(frames), b=np.stack(frames))
    elif case == "flat-array":
        raw.mkdir()
        np.save(raw / "wave.npy", np.stack(frames)[..., :2])
    elif case == "one-frame":
        raw.mkdir()
        np.save(raw / "wave.npy", np.stack(frames[:1]))
    elif case == "folder-and-array":
        write_frames(raw / "wave", frames, ".ply")
        np.save(raw / "wave.npy", np.stack(frames))
    elif case == "empty-folder":
        (raw / "wave").mkdir(parents=True)
    else:
        raise AssertionError(case)
