"""AIST++ (Li et al. 2021a) as downloaded: SMPL motions meshed with the user's SMPL model.

    AIST_ROOT/motions/<seq>.pkl    one dict per sequence: smpl_poses (T, 72) axis-angle, root
                                   first; smpl_trans (T, 3); smpl_scaling (1,); smpl_loss
    AIST_ROOT/ignore_list.txt      sequences whose fits AIST++ marks as bad, one a line

Every frame is meshed as the AIST++ API does: SMPL with zero betas (the dancers' shape is not in
the annotations), posed by `smpl_poses`, translated by `smpl_trans / smpl_scaling` (the fits
carry a per-sequence scale; dividing by it puts the translation in the generic SMPL body's
metres). The ground-truth joints are SMPL's 24 joints, `J_regressor` applied to the posed
vertices. The sequences in `ignore_list.txt` are left out; the split is the published one
(`nmjax.data.splits`). Motion files are pickles and are read with
`nmjax.data.body_models.restricted_load`, which loads arrays and nothing else.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from nmjax.data import body_models
from nmjax.data.streaming import SourceSequence, sample_mesh_sequence

MOTIONS = "motions"
IGNORE_LIST = "ignore_list.txt"
# What `nmjax.data.prepare.body_model_source` reads: the format's name in meta.json, the split
# rule, the summary's note on the sequences `list_sequences` leaves out, the model it needs.
FORMAT = "aist-motions"
PUBLISHED_SPLIT = True  # the published lists (nmjax.data.splits)
LEFT_OUT = "in ignore_list.txt, left out"
MODEL_KIND = "SMPL"
# Where the model comes from; printed when --body-model is missing or of the wrong kind.
MODEL_SOURCE = (
    "SMPL 1.1.0 for Python from https://smpl.is.tue.mpg.de (free registration; its licence "
    "forbids redistribution, so nmjax cannot ship it), e.g. SMPL_python_v.1.1.0/smpl/models/"
    "basicmodel_m_lbs_10_207_0_v1.1.0.pkl, or SMPL_MALE.pkl as the AIST++ API names it"
)
_CHUNK = 64  # frames posed at once: bounds the (chunk, 6890, 3, 4) skinning arrays


@dataclasses.dataclass(frozen=True)
class Motion:
    """One AIST++ motion file, checked.

    Attributes:
      poses: (T, 72) float64 axis-angle, 24 SMPL joints, root first.
      trans: (T, 3) float64 root translation, already divided by `smpl_scaling`.
    """

    poses: np.ndarray
    trans: np.ndarray

    @property
    def num_frames(self) -> int:
        return int(self.poses.shape[0])


def is_download(source: Path) -> bool:
    """True when `source` looks like the AIST++ annotations (it has a `motions/` folder)."""
    return (source / MOTIONS).is_dir()


def read_motion(path: Path) -> Motion:
    """Reads `motions/<seq>.pkl`.

    Raises:
      ValueError naming `path`: not a pickled dict of arrays, a missing key, shapes other than
        smpl_poses (T, 72), smpl_trans (T, 3), smpl_scaling one positive number, or NaN / inf.
    """
    with open(path, "rb") as f:
        content = body_models.restricted_load(f, path)
    if not isinstance(content, dict):
        raise ValueError(f"{path}: expected a pickled dict of arrays, got {type(content).__name__}")
    missing = [k for k in ("smpl_poses", "smpl_trans", "smpl_scaling") if k not in content]
    if missing:
        raise ValueError(f"{path}: no {', '.join(missing)}; is this an AIST++ motion file?")
    try:
        poses = np.asarray(content["smpl_poses"], dtype=np.float64)
        trans = np.asarray(content["smpl_trans"], dtype=np.float64)
        scaling = np.asarray(content["smpl_scaling"], dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{path}: smpl_poses / smpl_trans / smpl_scaling not numeric") from err
    num = poses.shape[0] if poses.ndim == 2 else -1
    if poses.shape != (num, 72) or num < 1 or trans.shape != (num, 3) or scaling.shape != (1,):
        raise ValueError(
            f"{path}: expected smpl_poses (T, 72), smpl_trans (T, 3) and one smpl_scaling, got "
            f"{poses.shape}, {trans.shape} and {scaling.shape}"
        )
    if not (np.isfinite(poses).all() and np.isfinite(trans).all() and scaling[0] > 0):
        raise ValueError(f"{path}: NaN / inf values, or smpl_scaling {scaling[0]} not positive")
    return Motion(poses=poses, trans=trans / scaling[0])


def read_ignore_list(source: Path) -> set[str]:
    """The sequence names in `source/ignore_list.txt` (empty when the file is absent)."""
    path = source / IGNORE_LIST
    if not path.is_file():
        return set()
    return {line.strip() for line in path.read_text().splitlines() if line.strip()}


def mesh_motion(
    model: body_models.BodyModel, motion: Motion, points: int, seeds: np.ndarray, where: str
) -> dict[str, np.ndarray]:
    """The first `len(seeds)` frames of `motion` as surface points and SMPL joints.

    Returns:
      {"joints": (T, 24, 3) float32 J_regressor of the posed vertices, "vertices": (T, points, 3)
      float32 area-uniform surface points, frame t sampled with seed `seeds[t]`}.
    """
    num = len(seeds)
    joints = np.empty((num, model.num_joints, 3), dtype=np.float32)
    vertices = np.empty((num, points, 3), dtype=np.float32)
    for start in range(0, num, _CHUNK):
        stop = min(start + _CHUNK, num)
        posed, _ = body_models.pose_model(
            model, motion.poses[start:stop], trans=motion.trans[start:stop]
        )
        joints[start:stop] = body_models.regress_joints(model.j_regressor, posed)
        vertices[start:stop] = sample_mesh_sequence(
            posed, model.faces, points, seeds[start:stop], f"{where} frames {start}-{stop - 1}"
        )
    return {"joints": joints, "vertices": vertices}


def list_sequences(
    source: Path, model: body_models.BodyModel
) -> tuple[list[SourceSequence], list[str]]:
    """Lists and checks every motion of the AIST++ folder `source` not in its ignore list.

    Every motion file is read once here, so that a damaged one is refused before anything is
    written; it is read again on its turn.

    Returns:
      (the sequences, sorted; the names left out by `ignore_list.txt`).

    Raises:
      FileNotFoundError: no `motions/*.pkl`.
      ValueError: a damaged motion file (named).
    """
    files = sorted((source / MOTIONS).glob("*.pkl"))
    if not files:
        raise FileNotFoundError(
            f"--from {source}: no {MOTIONS}/<seq>.pkl; expected the AIST++ annotations folder "
            f"(aist_plusplus_final/ with {MOTIONS}/ and {IGNORE_LIST})"
        )
    ignored = read_ignore_list(source)
    listed, left_out = [], []
    for path in files:
        if path.stem in ignored:
            left_out.append(path.stem)
            continue
        num_frames = read_motion(path).num_frames

        def read(points: int, seeds: np.ndarray, path: Path = path) -> dict[str, np.ndarray]:
            return mesh_motion(model, read_motion(path), points, seeds, str(path))

        listed.append(SourceSequence(path.stem, num_frames, read))
    return listed, left_out


def dataset_meta(model: body_models.BodyModel, ignored: list[str]) -> dict:
    """The meta.json entries an AIST++ set adds: the joints' names and tree, how it was meshed."""
    return {
        "body_model": str(model.path),
        "joint_names": list(body_models.SMPL_JOINT_NAMES),
        "parents": model.parents.tolist(),
        "meshing": "SMPL, zero betas, translation smpl_trans / smpl_scaling",
        "ignored": ignored,
    }
