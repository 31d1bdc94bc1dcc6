"""HanCo (Zimmermann et al. 2019, 2021) as downloaded: MANO fits meshed with the user's MANO model.

    HANCO_ROOT/meta.json                per sequence id sid and frame id fid: has_fit[sid][fid],
                                        is_valid[sid][fid], is_train, subject_id, ...
    HANCO_ROOT/shape/<sid>/<fid>.json   the MANO fit in world space: poses (1, 48) axis-angle,
                                        shapes (1, 10), global_t (1, 1, 3)
    HANCO_ROOT/xyz/<sid>/<fid>.json     the 21 hand keypoints in world space, metres

sid is written with 4 digits, fid with 8 (`shape/0012/00000034.json`). One sequence per sid,
named by it. A frame is kept where `has_fit` is true: those are the frames with a fit, which is
what meshing needs; HanCo's `is_valid` flag (its quality check of the fits) is not used, because
leaving its frames out would cut gaps into the motion that the trajectory loss and the dynamics
read frame to frame (the authors' HanCo preprocessing is not released, so the flag the paper used
is not known). The kept frames of a sid, in order, make its sequence; a sid with fewer than two
is left out. The split is 9:1 by frames over whole sequences, as the paper describes.

The fits store the pose relative to MANO's mean hand: the model's `hands_mean` is added to the 45
finger values (`body_models.mano_pose`); the mesh is posed about MANO's root joint and then moved
by `global_t`. The ground-truth joints are the `xyz` keypoints. Both must be in one frame and one
unit (MANO layers differ: some return millimetres), so every frame's keypoints are checked to lie
on the meshed hand (`check_keypoints`), and a sequence where they do not is refused.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from nmjax.data import body_models
from nmjax.data.streaming import SourceSequence, sample_mesh_sequence

META = "meta.json"
# What `nmjax.data.prepare.body_model_source` reads: the format's name in meta.json, the split
# rule, the summary's note on the sequences `list_sequences` leaves out, the model it needs.
FORMAT = "hanco-fits"
PUBLISHED_SPLIT = False  # none published: 9:1 by frames
LEFT_OUT = "sequences with fewer than 2 fitted frames, left out"
MODEL_KIND = "MANO"
# Where the model comes from; printed when --body-model is missing or of the wrong kind.
MODEL_SOURCE = (
    "MANO 1.2 from https://mano.is.tue.mpg.de (free registration; its licence forbids "
    "redistribution, so nmjax cannot ship it): mano_v1_2/models/MANO_RIGHT.pkl"
)
NUM_KEYPOINTS = 21
# The 21 keypoints: the wrist, then four per finger from the palm out to the tip.
KEYPOINT_NAMES = ("wrist",) + tuple(
    f"{finger}_{k}" for finger in ("thumb", "index", "middle", "ring", "pinky") for k in range(1, 5)
)
# Their tree, the wrist (the root) its own parent.
KEYPOINT_PARENTS = (0,) + tuple(0 if k == 0 else 4 * f + k for f in range(5) for k in range(4))
# The keypoints lie on or inside the hand: each within this fraction of the hand's size (its
# bounding-box diagonal) of a mesh vertex, and spread over 0.5 to 2 times that size. A millimetre
# / metre mix-up or another coordinate frame misses both by far.
NEAR_FRACTION = 0.2
SPREAD_RANGE = (0.5, 2.0)


def is_download(source: Path) -> bool:
    """True when `source` looks like HanCo: it has meta.json, or shape/ and xyz/ folders."""
    return (source / META).is_file() or ((source / "shape").is_dir() and (source / "xyz").is_dir())


def sequence_name(sid: int) -> str:
    return f"{sid:04d}"


def frame_file(source: Path, kind: str, sid: int, fid: int) -> Path:
    """`source/<kind>/<sid:04d>/<fid:08d>.json` (kind: shape or xyz)."""
    return source / kind / sequence_name(sid) / f"{fid:08d}.json"


def read_fitted_frames(source: Path) -> dict[int, list[int]]:
    """sid -> the frame ids whose `has_fit` is true, from `source/meta.json`.

    Raises:
      FileNotFoundError: no meta.json.
      ValueError: meta.json without a `has_fit` list of per-sequence lists.
    """
    path = source / META
    if not path.is_file():
        raise FileNotFoundError(
            f"--from {source}: no {META}; expected the HanCo root (with {META}, shape/ and xyz/)"
        )
    try:
        meta = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: unreadable ({err})") from err
    has_fit = meta.get("has_fit") if isinstance(meta, dict) else None
    if not isinstance(has_fit, list) or not all(isinstance(frames, list) for frames in has_fit):
        raise ValueError(f"{path}: expected 'has_fit': one list of per-frame flags per sequence")
    return {sid: [fid for fid, fit in enumerate(fits) if fit] for sid, fits in enumerate(has_fit)}


def _numbers(content: dict, key: str, size: int | None, path: Path) -> np.ndarray:
    try:
        values = np.asarray(content[key], dtype=np.float64).reshape(-1)
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"{path}: no numeric {key!r} ({err})") from err
    if (size is not None and values.shape != (size,)) or not np.isfinite(values).all():
        raise ValueError(f"{path}: {key!r} must hold {size} finite numbers, got {values.shape}")
    return values


def read_fit(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(pose (48,) relative to the mean hand, betas (B,), global_t (3,)) of one fit file."""
    try:
        content = json.loads(path.read_text())
    except FileNotFoundError as err:
        raise FileNotFoundError(f"{path}: missing; meta.json says this frame has a fit") from err
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: unreadable ({err})") from err
    if not isinstance(content, dict):
        raise ValueError(f"{path}: expected a JSON object with poses, shapes, global_t")
    return (
        _numbers(content, "poses", 48, path),
        _numbers(content, "shapes", None, path),
        _numbers(content, "global_t", 3, path),
    )


def read_keypoints(path: Path) -> np.ndarray:
    """(21, 3) keypoints of one xyz file."""
    try:
        keypoints = np.asarray(json.loads(path.read_text()), dtype=np.float64)
    except FileNotFoundError as err:
        raise FileNotFoundError(f"{path}: missing; meta.json says this frame has a fit") from err
    except (OSError, json.JSONDecodeError, TypeError, ValueError) as err:
        raise ValueError(f"{path}: unreadable keypoints ({err})") from err
    if keypoints.shape != (NUM_KEYPOINTS, 3) or not np.isfinite(keypoints).all():
        raise ValueError(
            f"{path}: expected {NUM_KEYPOINTS} finite [x, y, z] keypoints, got {keypoints.shape}"
        )
    return keypoints


def check_keypoints(vertices: np.ndarray, keypoints: np.ndarray, where: Path) -> None:
    """Refuses keypoints that do not lie on the meshed hand (another unit or frame).

    Args:
      vertices: (V, 3) the meshed hand of one frame.
      keypoints: (21, 3) that frame's keypoints.
      where: the keypoint file, for the message.

    Raises:
      ValueError naming `where`: a keypoint farther than NEAR_FRACTION of the hand's size from
        every vertex, or a keypoint spread outside SPREAD_RANGE times the hand's size.
    """
    size = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    spread = float(np.linalg.norm(np.ptp(keypoints, axis=0)))
    gaps = np.linalg.norm(keypoints[:, None, :] - vertices[None, :, :], axis=-1).min(axis=1)
    low, high = SPREAD_RANGE
    if gaps.max() > NEAR_FRACTION * size or not low * size <= spread <= high * size:
        raise ValueError(
            f"{where}: the keypoints do not lie on the hand meshed from its MANO fit (farthest "
            f"{gaps.max():.3g} from the mesh, which is {size:.3g} across; keypoints spread "
            f"{spread:.3g}); mesh and keypoints must share one frame and one unit: is the "
            "--body-model MANO_RIGHT.pkl as downloaded (metres)?"
        )


def mesh_fits(
    model: body_models.BodyModel,
    source: Path,
    sid: int,
    fids: list[int],
    points: int,
    seeds: np.ndarray,
) -> dict[str, np.ndarray]:
    """The first `len(seeds)` fitted frames `fids` of sequence `sid` as points and keypoints.

    Returns:
      {"joints": (T, 21, 3) float32 the xyz keypoints, "vertices": (T, points, 3) float32
      area-uniform surface points, frame t sampled with seed `seeds[t]`}.
    """
    fids = fids[: len(seeds)]
    fits = [read_fit(frame_file(source, "shape", sid, fid)) for fid in fids]
    pose = body_models.mano_pose(model, np.stack([fit[0] for fit in fits]))
    betas = np.zeros((len(fits), model.shapedirs.shape[-1]))
    for t, (_, shape, _) in enumerate(fits):
        if shape.shape[0] > betas.shape[1]:
            where = frame_file(source, "shape", sid, fids[t])
            raise ValueError(f"{where}: {shape.shape[0]} shapes, the model has {betas.shape[1]}")
        betas[t, : shape.shape[0]] = shape
    trans = np.stack([fit[2] for fit in fits])
    posed, _ = body_models.pose_model(model, pose, betas=betas, trans=trans)
    keypoints = np.empty((len(fids), NUM_KEYPOINTS, 3), dtype=np.float32)
    for t, fid in enumerate(fids):
        path = frame_file(source, "xyz", sid, fid)
        frame_keypoints = read_keypoints(path)
        check_keypoints(posed[t], frame_keypoints, path)
        keypoints[t] = frame_keypoints
    where = str(source / "shape" / sequence_name(sid))
    vertices = sample_mesh_sequence(posed, model.faces, points, seeds, where)
    return {"joints": keypoints, "vertices": vertices}


def list_sequences(
    source: Path, model: body_models.BodyModel
) -> tuple[list[SourceSequence], list[str]]:
    """Lists the HanCo sequences of `source` by its meta.json.

    Returns:
      (one sequence per sid with at least two fitted frames; the sids left out for fewer).

    Raises:
      FileNotFoundError / ValueError: no or a bad meta.json, no fitted frame at all.
    """
    fitted = read_fitted_frames(source)
    listed, left_out = [], []
    for sid, fids in fitted.items():
        if len(fids) < 2:
            left_out.append(sequence_name(sid))
            continue

        def read(points: int, seeds: np.ndarray, sid: int = sid, fids: list = fids) -> dict:
            return mesh_fits(model, source, sid, fids, points, seeds)

        listed.append(SourceSequence(sequence_name(sid), len(fids), read))
    if not listed:
        raise ValueError(f"{source / META}: no sequence has two or more frames with has_fit")
    return listed, left_out


def dataset_meta(model: body_models.BodyModel, unfitted: list[str]) -> dict:
    """The meta.json entries a HanCo set adds: the keypoints' names and tree, how it was meshed."""
    return {
        "body_model": str(model.path),
        "joint_names": list(KEYPOINT_NAMES),
        "parents": list(KEYPOINT_PARENTS),
        "meshing": "MANO, fit pose + hands_mean, fit shapes, + global_t; frames with has_fit",
        "fewer_than_two_fits": unfitted,
    }
