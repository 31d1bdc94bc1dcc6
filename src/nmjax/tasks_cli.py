"""The task subcommands on a phase-2 run folder (which records its phase-1 run):

    nmjax generate    --run RUN [--cond 5] [--gen 25] [--samples 3] [--inputs 2] [--voxels]
                      (--gen 300 works; past the end of a test sequence its observed panel holds)
    nmjax interpolate --run RUN [--gap 10] [--trajectories 16] [--inputs 2] [--vrnn-run RUN2]
    nmjax retarget    --run RUN --target MESH [--source SEQ] [--frames 30]

Inputs are the test-split keypoint trajectories of the phase-1 run (keypoints_test.npz). Each
command writes into `--out` (default `RUN/<command>`): the keypoints as .npz, a GIF of the motion
and a PNG strip of frames (matplotlib Agg, imageio), all atomically; `retarget` also writes one
.obj per frame.
"""

from __future__ import annotations

import argparse
import io as _io
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from nmjax import io, tasks
from nmjax.config import DynTrainConfig
from nmjax.train import common

COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")


# --- inputs ---------------------------------------------------------------------------------


def load_phase2(run: str | Path):
    """(dynamics model, its config, the phase-1 run folder) of a phase-2 run."""
    from nmjax.train import dyn

    run = Path(run)
    cfg = common.load_config(run, DynTrainConfig)
    if not cfg.skel_run:
        raise ValueError(f"{run}/config.json names no skel_run; is {run} a `train-dyn` run?")
    return dyn.restore_model(run), cfg, Path(cfg.skel_run)


def pick_inputs(
    trajectories: dict[str, np.ndarray], count: int, frames: int, names: list[str] | None = None
) -> tuple[list[str], np.ndarray]:
    """The first `count` sequences (sorted names, or `names`), frames 0..frames-1 of each.

    Sequences shorter than `frames` are padded with their last frame. Returns (names, (I, F, K, 4)).
    """
    chosen = sorted(trajectories) if names is None else names
    missing = [n for n in chosen if n not in trajectories]
    if missing:
        raise ValueError(f"no test sequence named {missing}; available: {sorted(trajectories)}")
    chosen = chosen[:count]
    crops = []
    for name in chosen:
        x = trajectories[name][:frames]
        if len(x) < frames:
            x = np.concatenate([x, np.repeat(x[-1:], frames - len(x), axis=0)])
        crops.append(x)
    return chosen, np.stack(crops).astype(np.float32)


# --- pictures -------------------------------------------------------------------------------


def _skeleton_axes(fig, rows: int, cols: int, index: int, lo, hi, title: str):
    ax = fig.add_subplot(rows, cols, index, projection="3d")
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(np.maximum(hi - lo, 1e-3))
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_zticks([])
    ax.set_title(title, fontsize=8)
    ax.view_init(elev=15, azim=-60)
    return ax


def _draw_pose(ax, pose: np.ndarray, parents, color: str, points: np.ndarray | None = None):
    if points is not None and len(points):
        ax.scatter(*points.T, s=0.5, c="0.65", alpha=0.3, depthshade=False)
    for k, p in enumerate(parents):
        if p != k:
            ax.plot(*zip(pose[p, :3], pose[k, :3], strict=True), "-", color=color, lw=1.5)
    ax.scatter(*pose[:, :3].T, s=6, c=color, depthshade=False)


def render_frames(
    motions: list[np.ndarray],
    labels: list[str],
    parents,
    clouds: list[np.ndarray | None] | None = None,
    size: float = 2.6,
) -> list[np.ndarray]:
    """One RGB image per frame with a 3D panel per motion.

    Args:
      motions: list of (T, K, >=3) joint positions (equal T).
      labels: panel titles.
      parents: (K,) the skeleton.
      clouds: optional per panel a (T, P, 3) point cloud drawn behind the skeleton.

    Returns:
      list of T (H, W, 3) uint8 images.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    extra = [c.reshape(-1, 3) for c in (clouds or []) if c is not None]
    stacked = np.concatenate([m[..., :3].reshape(-1, 3) for m in motions] + extra)
    lo, hi = stacked.min(0) - 0.05, stacked.max(0) + 0.05
    images = []
    for t in range(motions[0].shape[0]):
        fig = plt.figure(figsize=(size * len(motions), size))
        for i, (motion, label) in enumerate(zip(motions, labels, strict=True)):
            ax = _skeleton_axes(fig, 1, len(motions), i + 1, lo, hi, f"{label} t={t}")
            cloud = None if clouds is None or clouds[i] is None else clouds[i][t]
            _draw_pose(ax, motion[t], parents, COLORS[i % len(COLORS)], cloud)
        fig.tight_layout()
        fig.canvas.draw()
        images.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
        plt.close(fig)
    return images


def write_gif(path: Path, images: list[np.ndarray], fps: float = 8.0) -> None:
    """Animated GIF of equally sized RGB frames, written atomically."""
    import imageio.v3 as iio

    data = iio.imwrite("<bytes>", np.stack(images), extension=".gif", duration=1000 / fps, loop=0)
    with io.atomic_open(path, "wb") as f:
        f.write(data)


def write_strip(path: Path, images: list[np.ndarray], columns: int = 6) -> None:
    """PNG of `columns` frames spread over the sequence, stacked vertically, atomically."""
    import imageio.v3 as iio

    idx = np.unique(np.linspace(0, len(images) - 1, columns).astype(int))
    buffer = _io.BytesIO()
    iio.imwrite(buffer, np.concatenate([images[i] for i in idx], axis=0), extension=".png")
    with io.atomic_open(path, "wb") as f:
        f.write(buffer.getvalue())


def write_motion_pictures(
    stem: Path,
    motions: list[np.ndarray],
    labels: list[str],
    parents,
    clouds: list[np.ndarray | None] | None = None,
) -> None:
    """`stem`.gif (the whole motion) and `stem`.png (a strip of frames) of `render_frames`."""
    images = render_frames(motions, labels, parents, clouds=clouds)
    write_gif(stem.with_name(stem.name + ".gif"), images)
    write_strip(stem.with_name(stem.name + ".png"), images)


# --- generate -------------------------------------------------------------------------------


def run_generate(
    run: str | Path,
    *,
    cond: int = 5,
    gen: int = 25,
    samples: int = 3,
    inputs: int = 2,
    seed: int = 0,
    voxels: bool = False,
    out: str | Path | None = None,
) -> Path:
    """Motion generation for the first `inputs` test sequences; returns the output folder.

    Writes generate.npz (keypoints (I, S, T_cond + T_gen, K, 4), observed (I, T, K, 4) - the true
    continuation, padded with its last frame where the sequence is shorter (long horizons) -
    observed_frames (I,) the real frames of it, names, parents), optionally voxels.npz (decoded
    occupancy of every sample, uint8), and per input a GIF and PNG strip (observed next to the
    samples).
    """
    from nmjax.train import dyn

    model, cfg, skel_run = load_phase2(run)
    out = Path(out) if out is not None else Path(run) / "generate"
    trajectories = dyn.load_trajectories(skel_run, "test")
    names, observed = pick_inputs(trajectories, inputs, cond + gen)
    real_frames = np.array([min(len(trajectories[n]), cond + gen) for n in names], np.int32)
    graphdef, state = nnx.split(model)
    keypoints, _ = tasks.generate_jit(
        graphdef,
        state,
        jnp.asarray(observed[:, :cond]),
        jax.random.key(seed),
        num_frames=gen,
        num_samples=samples,
    )
    keypoints = np.asarray(keypoints)
    io.save_npz(
        out / "generate.npz",
        keypoints=keypoints,
        observed=observed,
        observed_frames=real_frames,
        names=np.array(names),
        parents=np.array(model.parents),
        cond=np.int32(cond),
    )
    if voxels:
        from nmjax.data.datasets import load_sequences
        from nmjax.evaluate import Detector, sequence_voxels

        detector = Detector.load(skel_run)
        data = detector.cfg.data
        seqs = {s.name: s for s in load_sequences(data.name, "test", data.root)}
        first = np.stack([sequence_voxels(seqs[n], data.sample_rate, data.grid)[0] for n in names])
        decoded = [detector.decode(keypoints[:, s], first) for s in range(samples)]
        io.save_npz(out / "voxels.npz", voxels=(np.stack(decoded, 1) >= 0.5).astype(np.uint8))
    for i, name in enumerate(names):
        motions = [observed[i]] + [keypoints[i, s] for s in range(samples)]
        held = real_frames[i] < cond + gen  # the sequence ends before the horizon
        labels = [f"observed (held from {real_frames[i]})" if held else "observed"]
        labels += [f"sample {s}" for s in range(samples)]
        write_motion_pictures(out / name, motions, labels, model.parents)
    return out


# --- interpolate ----------------------------------------------------------------------------


def run_interpolate(
    run: str | Path,
    *,
    gap: int = 10,
    trajectories: int = 16,
    inputs: int = 2,
    vrnn_run: str | Path | None = None,
    seed: int = 0,
    out: str | Path | None = None,
) -> Path:
    """Interpolation between frames 0 and `gap` of the first `inputs` test sequences.

    Writes interpolate.npz ({method: (I, gap + 1, K, 4)}, "truth", names, parents) and per input a
    GIF and PNG strip with one panel per method and the truth.
    """
    from nmjax.evaluate import Interpolators
    from nmjax.train import dyn

    model, cfg, skel_run = load_phase2(run)
    out = Path(out) if out is not None else Path(run) / "interpolate"
    names, truth = pick_inputs(dyn.load_trajectories(skel_run, "test"), inputs, gap + 1)
    vrnn = None if vrnn_run is None else nnx.split(dyn.restore_model(vrnn_run))
    interp = Interpolators(nnx.split(model), vrnn, trajectories)
    methods = ["Ours"] + (["VRNN"] if vrnn is not None else []) + ["Lerp", "Slerp"]
    key = jax.random.key(seed)
    results = {m: interp.run(m, truth[:, 0], truth[:, -1], gap, key) for m in methods}
    io.save_npz(
        out / "interpolate.npz",
        truth=truth,
        names=np.array(names),
        parents=np.array(model.parents),
        **results,
    )
    for i, name in enumerate(names):
        motions = [truth[i]] + [results[m][i] for m in methods]
        write_motion_pictures(out / name, motions, ["truth", *methods], model.parents)
    return out


# --- retarget -------------------------------------------------------------------------------


def detect_target_joints(detector, points: np.ndarray) -> np.ndarray:
    """Keypoints (K, 4) of one normalised point cloud, the frame repeated over a T-frame crop."""
    from nmjax.data.voxelize import voxelize

    cfg = detector.cfg
    grid = voxelize(points, cfg.data.grid)
    crop = np.broadcast_to(grid, (1, cfg.data.frames, *grid.shape))
    keypoints, _ = detector.run_batches(np.ascontiguousarray(crop))
    return keypoints[0, 0]


def write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """A triangle mesh as Wavefront .obj text, atomically."""
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    io.write_text(path, "\n".join(lines) + "\n")


def run_retarget(
    run: str | Path,
    target: str | Path,
    *,
    source: str | None = None,
    frames: int = 30,
    points: int = 20000,
    seed: int = 0,
    out: str | Path | None = None,
) -> Path:
    """Retargets a test motion of the run onto a target mesh (Fig. 6, appendix D.4).

    1. Target skeleton: `points` surface samples of the mesh, normalised (DESIGN section 4),
       voxelised, keypoints by the phase-1 detector; topology = the run's skeleton.
    2. Source motion: local rotations and root trajectory inferred by the dynamics posterior
       (best of S) from the source keypoints.
    3. Eqs. 24-25 give the retargeted joints; target rest rotations are the posterior's rotations
       of the target pose, corrected onto its bones (`tasks.rest_rotations`).
    4. Skin weights (Algorithm 2, the run's keypoint intensities for pruning) and LBS; the result
       is mapped back to the mesh's units and written as frame_XXXX.obj plus a GIF.

    Returns:
      the output folder.
    """
    from nmjax.evaluate import Detector
    from nmjax.skeleton import load_skeleton, skin_weights
    from nmjax.train import dyn

    mesh = tasks.load_mesh(target)
    model, cfg, skel_run = load_phase2(run)
    out = Path(out) if out is not None else Path(run) / f"retarget-{Path(target).stem}"
    trajectories = dyn.load_trajectories(skel_run, "test")
    names = None if source is None else [source]
    (name,), x_src = pick_inputs(trajectories, 1, frames, names)
    skeleton = load_skeleton(skel_run / "skeleton.json")
    intensities = json.loads((skel_run / "skeleton.json").read_text()).get("intensities")

    # Target pose in its own normalised frame.
    bmin, scale = tasks.normalization_of(mesh.vertices)
    cloud = (tasks.sample_mesh_points(mesh, points, seed) - bmin) * scale - 1.0
    detector = Detector.load(skel_run)
    target_kp = detect_target_joints(detector, cloud.astype(np.float32))
    vertices = (np.asarray(mesh.vertices) - bmin) * scale - 1.0

    graphdef, state = nnx.split(model)
    key_src, key_tar = jax.random.split(jax.random.key(seed))
    src_rot, src_rec = tasks.infer_rotations_jit(graphdef, state, jnp.asarray(x_src), key_src)
    tar_in = jnp.asarray(np.repeat(target_kp[None, None], 2, axis=1))
    tar_rot, _ = tasks.infer_rotations_jit(graphdef, state, tar_in, key_tar)
    parents, order, root = model.parents, model.order, model.order[0]
    directions = model.directions[...]
    target_mu = jnp.asarray(target_kp[:, :3])
    _, tar_glob = tasks.retarget_joints(
        target_mu[root][None], tar_rot[0, :1], directions, target_mu, parents, order
    )
    rest_rot = tasks.rest_rotations(jnp.asarray(target_kp[:, :3]), tar_glob[0], directions, parents)
    root_path = (
        jnp.asarray(target_kp[root, :3]) + src_rec[0, :, root, :3] - src_rec[0, :1, root, :3]
    )
    joints, glob = tasks.retarget_joints(
        root_path, src_rot[0], directions, jnp.asarray(target_kp[:, :3]), parents, order
    )
    weights = skin_weights(vertices, target_kp[:, :3], skeleton, intensities=intensities)
    moved = tasks.retarget_vertices(
        jnp.asarray(vertices, jnp.float32),
        jnp.asarray(weights),
        jnp.asarray(target_kp[:, :3]),
        rest_rot,
        joints,
        glob,
    )
    moved_mesh = (np.asarray(moved, np.float64) + 1.0) / scale + bmin  # back to mesh units
    faces = np.asarray(mesh.faces)
    for t, verts in enumerate(moved_mesh):
        write_obj(out / f"frame_{t:04d}.obj", verts, faces)
    joints_mesh = (np.asarray(joints) + 1.0) / scale + bmin
    src_mu = np.asarray(x_src[0])
    io.save_npz(
        out / "retarget.npz",
        source_keypoints=src_mu,
        target_keypoints=target_kp,
        joints=joints_mesh.astype(np.float32),
        skin_weights=weights,
        parents=np.array(parents),
        source=np.array(name),
    )
    # Pictures in the normalised frames (source and target each in their own [-1, 1] cube).
    sub = np.random.default_rng(seed).choice(len(faces), min(len(faces), 1500), replace=False)
    tri_centres = np.asarray(moved)[:, faces[sub]].mean(axis=2)  # (T, P, 3) a surface sketch
    write_motion_pictures(
        out / "retarget",
        [src_mu, np.asarray(joints)],
        [f"source {name}", f"retargeted {Path(target).name}"],
        parents,
        clouds=[None, tri_centres],
    )
    return out


# --- argument parsing -----------------------------------------------------------------------


def _parser(prog: str, description: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=f"nmjax {prog}", description=description)
    parser.add_argument("--run", required=True, help="phase-2 run folder (train-dyn, model nm)")
    parser.add_argument("--out", default=None, help=f"output folder (default RUN/{prog})")
    parser.add_argument("--seed", type=int, default=0)
    return parser


def _parse_and_run(parser: argparse.ArgumentParser, argv: list[str], fn, positive=()) -> int:
    """Parses `argv`, checks the `positive` options are >= 1 and calls `fn(**options)`.

    Every option of the parser is passed to `fn` under its destination name, so the parser and
    the task function must agree on names. Returns the exit status: 0, or 1 after printing a
    FileNotFoundError / ValueError raised by the task.
    """
    args = parser.parse_args(argv)
    for name in positive:
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    try:
        out = fn(**vars(args))
    except (FileNotFoundError, ValueError) as err:
        print(f"{parser.prog}: {err}", file=sys.stderr)
        return 1
    print(f"{parser.prog}: wrote {out}")
    return 0


def generate_main(argv: list[str]) -> int:
    parser = _parser("generate", "Sample T_gen future frames after T_cond observed frames.")
    parser.add_argument("--cond", type=int, default=5, help="T_cond observed frames")
    parser.add_argument("--gen", type=int, default=25, help="T_gen generated frames")
    parser.add_argument("--samples", type=int, default=3, help="futures per input")
    parser.add_argument("--inputs", type=int, default=2, help="test sequences used as inputs")
    parser.add_argument("--voxels", action="store_true", help="also decode voxels (phase-1)")
    return _parse_and_run(parser, argv, run_generate, ("cond", "gen", "samples", "inputs"))


def interpolate_main(argv: list[str]) -> int:
    parser = _parser("interpolate", "Interpolate between keyframes 0 and GAP of test sequences.")
    parser.add_argument("--gap", type=int, default=10, help="frames between the keyframes (SR)")
    parser.add_argument("--trajectories", type=int, default=16, help="rollouts to choose from")
    parser.add_argument("--inputs", type=int, default=2, help="test sequences")
    parser.add_argument("--vrnn-run", default=None, help="positional VRNN run for the baseline")
    return _parse_and_run(parser, argv, run_interpolate, ("gap", "trajectories", "inputs"))


def retarget_main(argv: list[str]) -> int:
    parser = _parser("retarget", "Retarget a test motion onto a mesh (Eqs. 24-25, LBS).")
    parser.add_argument("--target", required=True, help="target mesh (.obj, .ply, ...)")
    parser.add_argument("--source", default=None, help="test sequence name (default: first)")
    parser.add_argument("--frames", type=int, default=30, help="frames of the source motion")
    parser.add_argument("--points", type=int, default=20000, help="points sampled on the mesh")
    return _parse_and_run(parser, argv, run_retarget, ("frames", "points"))
