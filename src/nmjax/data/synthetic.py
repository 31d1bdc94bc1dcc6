"""Built-in synthetic articulated datasets: the bodies of `nmjax.data.bodies` in motion (C4).

A fresh clone can train without downloading anything: `ensure_dataset("synth-hand")` (or
`nmjax prepare-data --data synth-hand`) writes a set in the layout every loader reads
(`nmjax.data.layout`),

    <root>/<split>/vertices/<seq>.npy   (T, N, 3) float32  surface points, N = 20,000 by default
    <root>/<split>/joints/<seq>.npy     (T, J, 3) float32  ground-truth joint positions
    <root>/<split>/angles/<seq>.npy     (T, D) float32     the joint-angle trajectory that posed it
    <root>/split.json                   {"train": [...], "test": [...]}  (9:1 by sequence count)
    <root>/meta.json                    joint names, parents (root is its own parent), ... and
                                        "complete": true, written last

Generating is always an explicit call (`generate`, or `ensure_dataset`, which generates only a
set that is missing or unfinished); the loaders never write. A sequence is made by

  1. drawing a smooth joint-angle trajectory within the joint limits (`sample_motion`): every
     degree of freedom follows a normalised sum of three random sinusoids, optionally mixed with a
     signal shared by its group (a finger's curl, the hand's spread, a gait phase), mapped into a
     random sub-range of its limits and clipped to them;
  2. posing the joints by forward kinematics (`pose`, NumPy, vectorised over frames);
  3. sampling surface points area-uniformly (`sample_body_surface`): the links are rigid, so
     triangles are drawn on the rest-pose link meshes with probability proportional to their area,
     and the samples are carried into every frame by their joint's rotation and position. (A
     single mesh frame of a real dataset is sampled by `nmjax.data.meshes.sample_surface`.)

Everything is deterministic for a seed: the set's generator `np.random.default_rng(seed)` draws the
sequence lengths and spawns one child generator per sequence, so the same seed gives the same
bytes.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from tqdm import tqdm

from nmjax.data import layout
from nmjax.data.bodies import Body, Joint, get_body
from nmjax.geometry import axis_angle_to_matrix_np, forward_kinematics_np

# --------------------------------------------------------------------------------------------
# Motion, kinematics and surface sampling


def _smooth_signals(
    rng: np.random.Generator, count: int, frames: int, period: tuple[float, float]
) -> np.ndarray:
    """(count, frames) smooth signals spanning [-1, 1]: sums of three random sinusoids.

    Each sum is stretched to run from exactly -1 to 1 over the sequence, so that every degree of
    freedom sweeps its whole sampled sub-range (a visible motion) however short the sequence.
    """
    t = np.arange(frames, dtype=np.float64)
    weights = rng.uniform(0.2, 1.0, size=(count, 3))
    freqs = 1.0 / rng.uniform(*period, size=(count, 3))
    phases = rng.uniform(0.0, 2 * np.pi, size=(count, 3))
    waves = np.sin(2 * np.pi * freqs[..., None] * t + phases[..., None])  # (count, 3, frames)
    sums = np.einsum("ck,ckt->ct", weights, waves)
    low, high = sums.min(-1, keepdims=True), sums.max(-1, keepdims=True)
    return 2.0 * (sums - low) / np.maximum(high - low, 1e-12) - 1.0


def sample_motion(
    body: Body, frames: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Draws one smooth random motion of `body` within its joint limits.

    Every degree of freedom mixes its own signal with its group's, c = w g + (1 - |w|) s in [-1, 1],
    and maps it into a random sub-range of its limits: angle = mid + half (c0 + a c) with amplitude
    a ~ U(0.5, 1) and centre c0 ~ U(-(1 - a), 1 - a), clipped to the limits. The root drifts
    forward along its (horizontal) local x axis at a random speed up to `body.speed` and wanders
    smoothly by up to `body.wander` per axis.

    Args:
      body: the body.
      frames: number of frames T.
      rng: random generator.

    Returns:
      angles (T, D) in the column order of `body.dofs`, root translation (T, 3).
    """
    dofs = body.dofs
    groups = sorted({d.group for _, d in dofs if d.group is not None})
    own = _smooth_signals(rng, len(dofs), frames, body.period)  # (D, T)
    shared = dict(zip(groups, _smooth_signals(rng, len(groups), frames, body.period), strict=True))
    coupling = np.array([d.coupling if d.group else 0.0 for _, d in dofs])[:, None]
    group_signal = np.stack([shared[d.group] if d.group else np.zeros(frames) for _, d in dofs])
    mixed = coupling * group_signal + (1.0 - np.abs(coupling)) * own
    amplitude = rng.uniform(0.5, 1.0, size=(len(dofs), 1))
    centre = rng.uniform(-1.0, 1.0, size=(len(dofs), 1)) * (1.0 - amplitude)
    limits = body.limits
    mid, half = limits.mean(-1, keepdims=True), (limits[:, 1:] - limits[:, :1]) / 2
    angles = np.clip(mid + half * (centre + amplitude * mixed), limits[:, :1], limits[:, 1:]).T

    wander = _smooth_signals(rng, 3, frames, body.period).T * np.asarray(body.wander)  # (T, 3)
    speed = rng.uniform(0.0, body.speed)
    root_rotation = _local_rotations(body.joints[0], angles[:, : len(body.joints[0].dofs)])
    heading = root_rotation[:, :, 0] * np.array([1.0, 1.0, 0.0])  # local x, made horizontal
    heading /= np.maximum(np.linalg.norm(heading, axis=-1, keepdims=True), 1e-9)
    drift = np.cumsum(speed * heading, axis=0) - speed * heading[:1]
    return angles, wander - wander[:1] + drift


def _euler(rest: Sequence[float]) -> np.ndarray:
    """(3, 3) rotation Rz @ Ry @ Rx of Euler angles (x, y, z)."""
    rx, ry, rz = (axis_angle_to_matrix_np(a, r) for a, r in zip(np.eye(3), rest, strict=True))
    return rz @ ry @ rx


def _local_rotations(joint: Joint, angles: np.ndarray) -> np.ndarray:
    """(T, 3, 3) rest rotation times the joint's rotations, for its angle columns (T, D_j)."""
    rotation = np.broadcast_to(_euler(joint.rest), (angles.shape[0], 3, 3))
    for column, dof in enumerate(joint.dofs):
        if dof.kind == "rotate":
            rotation = rotation @ axis_angle_to_matrix_np(dof.axis, angles[:, column])
    return rotation


def pose(
    body: Body, angles: np.ndarray, root_translation: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Forward kinematics: joint positions and frames for every frame.

    p_j = p_parent + R_parent (offset_j + Rest_j sum_slide theta axis),
    R_j = R_parent Rest_j prod_rotate R(axis, theta); the root's parent frame is the world moved by
    `root_translation` (`geometry.forward_kinematics_np`, offsets in the parent's frame).

    Args:
      body: the body.
      angles: (T, D) in the column order of `body.dofs`.
      root_translation: (T, 3).

    Returns:
      positions (T, J, 3) and world rotations (T, J, 3, 3) of the joints.
    """
    angles = np.asarray(angles, dtype=np.float64)
    frames = angles.shape[0]
    if angles.shape != (frames, len(body.dofs)):
        raise ValueError(
            f"angles must have shape (T, {len(body.dofs)}) for {body.name}, got {angles.shape}"
        )
    offsets = np.zeros((frames, len(body.joints), 3))
    local = np.zeros((frames, len(body.joints), 3, 3))
    start = 0
    for j, joint in enumerate(body.joints):  # the joints' own degrees of freedom, vectorised over T
        cols = angles[:, start : start + len(joint.dofs)]
        start += len(joint.dofs)
        slide_axes = np.array(
            [d.axis if d.kind == "slide" else (0.0, 0.0, 0.0) for d in joint.dofs]
        ).reshape(-1, 3)
        offsets[:, j] = np.asarray(joint.offset) + cols @ slide_axes @ _euler(joint.rest).T
        local[:, j] = _local_rotations(joint, cols)
    root = np.asarray(root_translation, np.float64) + offsets[:, 0]
    order = np.arange(len(body.joints))  # every parent is listed before its children
    return forward_kinematics_np(root, local, offsets, body.parents, order, offset_frame="parent")


@functools.cache
def body_triangles(body: Body) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of every link in its joint's frame: (F, 3, 3) corners and (F,) joint index."""
    triangles, owner = [], []
    for j, joint in enumerate(body.joints):
        for link in joint.links:
            mesh = link.mesh()
            triangles.append(np.asarray(mesh.triangles, dtype=np.float64))
            owner.append(np.full(len(mesh.faces), j))
    return np.concatenate(triangles), np.concatenate(owner)


def rest_mesh(body: Body) -> trimesh.Trimesh:
    """The body's surface (all links, not merged) with every angle zero, for tests and pictures."""
    positions, rotations = pose(body, np.zeros((1, len(body.dofs))), np.zeros((1, 3)))
    triangles, owner = body_triangles(body)
    world = np.einsum("fij,fcj->fci", rotations[0, owner], triangles) + positions[0, owner, None]
    return trimesh.Trimesh(**trimesh.triangles.to_kwargs(world))


def sample_body_surface(
    body: Body,
    positions: np.ndarray,
    rotations: np.ndarray,
    points: int,
    rng: np.random.Generator,
    chunk: int = 16,
) -> np.ndarray:
    """Area-uniform surface samples of the posed body, drawn independently for every frame.

    Rigid links keep their area, so a triangle is picked with probability proportional to its
    rest-pose area, a point uniformly inside it (u = sqrt(r1): (1-u) A + u (1-r2) B + u r2 C), and
    the point is carried by its joint's transform. Frames go in chunks to bound memory.

    Args:
      body: the body.
      positions: (T, J, 3) joint positions from `pose`.
      rotations: (T, J, 3, 3) joint rotations from `pose`.
      points: N, samples per frame.
      rng: random generator.
      chunk: frames transformed at once.

    Returns:
      (T, N, 3) float32 points.
    """
    triangles, owner = body_triangles(body)
    areas = np.linalg.norm(
        np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]), axis=-1
    )
    cumulative = np.cumsum(areas)
    out = np.empty((positions.shape[0], points, 3), dtype=np.float32)
    for start in range(0, positions.shape[0], chunk):
        stop = min(start + chunk, positions.shape[0])
        shape = (stop - start, points)
        face = np.minimum(
            np.searchsorted(cumulative, rng.random(shape) * cumulative[-1], side="right"),
            len(areas) - 1,
        )
        u, r2 = np.sqrt(rng.random(shape))[..., None], rng.random(shape)[..., None]
        tri = triangles[face]  # (t, N, 3, 3)
        local = (1 - u) * tri[..., 0, :] + u * (1 - r2) * tri[..., 1, :] + u * r2 * tri[..., 2, :]
        frame = np.arange(start, stop)[:, None]
        joint = owner[face]
        world = np.einsum("tnij,tnj->tni", rotations[frame, joint], local) + positions[frame, joint]
        out[start:stop] = world
    return out


@dataclass(frozen=True)
class SyntheticSequence:
    """One generated sequence: surface points (T, N, 3) float32, joints (T, J, 3) float32,
    angles (T, D) float32 and root translation (T, 3) float32."""

    vertices: np.ndarray
    joints: np.ndarray
    angles: np.ndarray
    root_translation: np.ndarray


def simulate(
    name: str, frames: int, *, points: int = 20000, rng: np.random.Generator | int = 0
) -> SyntheticSequence:
    """Draws a motion of body `name`, poses it and samples its surface (steps 1-3 of the module)."""
    body = get_body(name)
    if frames < 1 or points < 1:
        raise ValueError(
            f"frames and points must be positive, got frames={frames}, points={points}"
        )
    rng = np.random.default_rng(rng) if isinstance(rng, int) else rng
    angles, root = sample_motion(body, frames, rng)
    positions, rotations = pose(body, angles, root)
    vertices = sample_body_surface(body, positions, rotations, points, rng)
    return SyntheticSequence(
        vertices, positions.astype(np.float32), angles.astype(np.float32), root.astype(np.float32)
    )


# --------------------------------------------------------------------------------------------
# Writing a set


def generate(
    name: str,
    root: str | Path,
    *,
    num_sequences: int | None = None,
    frames: int | None = None,
    points: int = 20000,
    seed: int = 0,
    progress: bool = True,
) -> Path:
    """Writes synthetic dataset `name` into `root` in the nmjax layout (see the module docstring).

    meta.json is removed first and written last with "complete": true, so an interrupted run never
    looks finished (`layout.is_complete`); every file is written atomically. Sequence files left
    from an earlier, larger set in `root` are deleted. Same arguments, same bytes.

    Args:
      name: one of `BODIES` ("synth-hand", "synth-arm", "synth-human", "synth-quadruped").
      root: the dataset folder, e.g. data/synth-hand.
      num_sequences: number of sequences (default: the body's, 30); 9:1 train/test, >= 1 test.
      frames: frames per sequence (default: random per sequence in the body's range, 50-80).
      points: surface points per frame.
      seed: seed of the whole set.
      progress: show a tqdm bar over sequences.

    Returns:
      `root` as a Path.
    """
    body = get_body(name)
    num_sequences = body.num_sequences if num_sequences is None else int(num_sequences)
    splits = layout.split_names(num_sequences)
    if frames is not None and frames < 2:
        raise ValueError(f"frames must be at least 2 (a sequence needs motion), got {frames}")
    if points < 1:
        raise ValueError(f"points must be positive, got {points}")
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    (root / "meta.json").unlink(missing_ok=True)

    rng = np.random.default_rng(seed)
    if frames is None:
        lengths = rng.integers(body.frames[0], body.frames[1] + 1, size=num_sequences)
    else:
        lengths = np.full(num_sequences, frames)
    children = rng.spawn(num_sequences)
    jobs = [(split, seq) for split in layout.SPLITS for seq in splits[split]]
    for index, (split, seq) in enumerate(
        tqdm(jobs, desc=f"generating {name}", unit="seq", disable=not progress)
    ):
        sequence = simulate(name, int(lengths[index]), points=points, rng=children[index])
        layout.write_sequence(
            root,
            split,
            seq,
            vertices=sequence.vertices,
            joints=sequence.joints,
            angles=sequence.angles,
        )
    for split in layout.SPLITS:
        for kind in ("vertices", "joints", "angles"):
            for path in (root / split / kind).glob("*.npy"):
                if layout.GENERATED_NAME.fullmatch(path.stem) and path.stem not in splits[split]:
                    path.unlink()
    layout.write_index(
        root,
        splits,
        {
            "name": name,
            "joint_names": body.joint_names,
            "parents": body.parents,
            "joint_radius": [j.radius for j in body.joints],
            "dofs": [
                {
                    "joint": body.joints[j].name,
                    "kind": d.kind,
                    "axis": list(d.axis),
                    "limits": [d.lower, d.upper],
                }
                for j, d in body.dofs
            ],
            "sample_rate": 1,
            "seed": seed,
            "num_sequences": num_sequences,
            "frames": {seq: int(lengths[i]) for i, (_, seq) in enumerate(jobs)},
            "points": points,
            "generator": "nmjax.data.synthetic",
            "complete": True,
        },
    )
    return root


def ensure_dataset(name: str, root: str | os.PathLike | None = None, **options) -> Path:
    """The folder of dataset `name`, generating it first when it is a synthetic set not yet there.

    This is the one step that writes a synthetic set on demand: callers that train or benchmark on
    a dataset call it before loading, and the loaders themselves never generate. A synthetic set is
    (re)generated when `layout.is_complete` says its folder holds no finished set (missing, or an
    interrupted generation); a finished set is left as it is, whatever `options` say. Real datasets
    are prepared with `nmjax prepare-data --from DIR`; for them this only resolves the folder, and
    loading reports what is missing.

    Args:
      name: a registered dataset (`nmjax.config.DATASETS`).
      root: dataset folder; default `layout.dataset_root(name)`.
      **options: passed to `generate` when it runs (num_sequences, frames, points, seed, progress).

    Returns:
      the dataset folder.
    """
    folder = layout.dataset_root(name, root)
    if name in layout.SYNTHETIC_DATASETS and not layout.is_complete(folder):
        generate(name, folder, **options)
    return folder
