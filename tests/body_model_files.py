"""Tiny SMPL-family model files for the tests, written as users get them: an `.npz` of arrays, and
a `.pkl` in the official files' form (protocol 2, arrays wrapped in chumpy objects, J_regressor a
scipy sparse matrix). chumpy itself is not needed: `chumpy_modules` puts a stand-in class named
`chumpy.ch.Ch` in place while pickling, which pickles the way chumpy does (class + attribute dict
with the array under "x").
"""

from __future__ import annotations

import contextlib
import pickle
import sys
import types
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import scipy.sparse

# SMPL's 24-joint tree and MANO's 16-joint tree (wrist, then index, middle, pinky, ring, thumb).
SMPL_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21]
MANO_PARENTS = [-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 0, 10, 11, 0, 13, 14]
ROOT_ID = 2**32 - 1  # how SMPL's kintree_table marks the root's missing parent (uint32)


class Ch:
    """Pickles like a chumpy array: its class, then its attribute dict holding the array as "x"."""

    __module__, __qualname__ = "chumpy.ch", "Ch"

    def __init__(self, x: np.ndarray):
        self.x = x
        self._dirty_vars = set()


class ChAdd:
    """A chumpy expression (a sum of two arrays): pickled state without "x"."""

    __module__, __qualname__ = "chumpy.ch_ops", "add"

    def __init__(self, a: Ch, b: Ch):
        self.a, self.b = a, b


@contextlib.contextmanager
def chumpy_modules() -> Iterator[None]:
    """Makes `Ch` and `ChAdd` picklable under chumpy's module names for the duration."""
    ch, ops = types.ModuleType("chumpy.ch"), types.ModuleType("chumpy.ch_ops")
    ch.Ch, ops.add = Ch, ChAdd
    saved = {name: sys.modules.get(name) for name in ("chumpy", "chumpy.ch", "chumpy.ch_ops")}
    sys.modules.update(chumpy=types.ModuleType("chumpy"), **{"chumpy.ch": ch, "chumpy.ch_ops": ops})
    try:
        yield
    finally:
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module


def kintree(parents: list[int]) -> np.ndarray:
    """SMPL's (2, K) uint32 table: row 0 the parent ids (root: 2**32 - 1), row 1 the joint ids."""
    parent_ids = [ROOT_ID if p < 0 else p for p in parents]
    return np.array([parent_ids, list(range(len(parents)))], dtype=np.uint32)


def chain_model(posedirs_scale: float = 0.0, seed: int = 0) -> dict[str, np.ndarray]:
    """A two-bone chain along x: joints 0, 1, 2 at x = 0, 1, 2 (0 the root, 2 the tip).

    Vertices 0-2 are markers at the joints (J_regressor picks them, each weighted to its joint);
    vertex 3 = (0.5, 0.1, 0) follows joint 0, vertex 4 = (1.5, 0.1, 0) joint 1, vertex 5 =
    (1.5, -0.1, 0) half joint 0 and half joint 1, vertex 6 = (2.5, 0, 0) joint 2.
    """
    rng = np.random.default_rng(seed)
    v_template = np.array(
        [[0, 0, 0], [1, 0, 0], [2, 0, 0], [0.5, 0.1, 0], [1.5, 0.1, 0], [1.5, -0.1, 0]]
        + [[2.5, 0, 0]],
        dtype=np.float64,
    )
    weights = np.zeros((7, 3))
    weights[[0, 1, 2, 3, 4, 6], [0, 1, 2, 0, 1, 2]] = 1.0
    weights[5, :2] = 0.5
    j_regressor = np.zeros((3, 7))
    j_regressor[[0, 1, 2], [0, 1, 2]] = 1.0
    return {
        "v_template": v_template,
        "shapedirs": rng.normal(size=(7, 3, 2)),
        "posedirs": posedirs_scale * rng.normal(size=(7, 3, 18)),
        "J_regressor": j_regressor,
        "kintree_table": kintree([-1, 0, 1]),
        "weights": weights,
        "f": np.array([[0, 3, 4], [1, 4, 5], [2, 5, 6]], dtype=np.uint32),
    }


def box_model(
    parents: list[int], joints: np.ndarray, half: float, betas: int = 3, seed: int = 0
) -> dict[str, np.ndarray]:
    """A box of half-size `half` around every joint, skinned rigidly to it (no pose blend shapes).

    J_regressor averages each box's 8 corners, so the regressed joints of any posed mesh are its
    posed chain joints. Shape blend shapes move every joint's box as a whole.
    """
    rng = np.random.default_rng(seed)
    num = len(parents)
    corners = half * np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
    v_template = (joints[:, None, :] + corners).reshape(-1, 3)
    cube = np.array(
        [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1]]
        + [[2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    )
    faces = (cube[None] + 8 * np.arange(num)[:, None, None]).reshape(-1, 3)
    weights = np.repeat(np.eye(num), 8, axis=0)
    shift = rng.normal(scale=half, size=(num, 3, betas))
    return {
        "v_template": v_template,
        "shapedirs": np.repeat(shift, 8, axis=0),
        "posedirs": np.zeros((8 * num, 3, 9 * (num - 1))),
        "J_regressor": weights.T / 8.0,
        "kintree_table": kintree(parents),
        "weights": weights,
        "f": faces.astype(np.uint32),
    }


def tree_joints(parents: list[int], bone: float, seed: int = 0) -> np.ndarray:
    """Rest joints of a tree: each joint `bone` from its parent, in a random direction about +x."""
    rng = np.random.default_rng(seed)
    joints = np.zeros((len(parents), 3))
    for joint, parent in enumerate(parents):
        if parent >= 0:
            step = rng.normal(size=3) + np.array([2.0, 0.0, 0.0])
            joints[joint] = joints[parent] + bone * step / np.linalg.norm(step)
    return joints


def write_npz(path: Path, arrays: dict[str, np.ndarray]) -> Path:
    np.savez(path, **arrays)
    return path


def write_official_pkl(path: Path, arrays: dict[str, np.ndarray], protocol: int = 2) -> Path:
    """The form of the official files: a pickled dict (protocol 2, or Python 2's default 0);
    v_template, shapedirs, posedirs and weights as chumpy arrays, J_regressor as a scipy
    csc_matrix, a chumpy expression under "J" that nothing reads, plus the strings the official
    files carry."""
    content: dict[str, object] = dict(arrays)
    with chumpy_modules():
        for key in ("v_template", "shapedirs", "posedirs", "weights"):
            content[key] = Ch(arrays[key])
        content["J_regressor"] = scipy.sparse.csc_matrix(arrays["J_regressor"])
        content["J"] = ChAdd(Ch(arrays["v_template"][:1]), Ch(arrays["v_template"][:1]))
        content["bs_style"], content["bs_type"] = "lbs", "lrotmin"
        with open(path, "wb") as f:
            pickle.dump(content, f, protocol=protocol)
    return path
