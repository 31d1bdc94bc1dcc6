"""SMPL and MANO in NumPy, from the model file the user obtained from the model's owners.

The forward pass is the one both models share (SMPL: Loper et al. 2015, Sec. 3; MANO: Romero et
al. 2017, which reuses it with 16 hand joints):

    v_shaped = v_template + shapedirs . betas                     shape blend
    J        = J_regressor . v_shaped                             rest-pose joints
    v_posed  = v_shaped + posedirs . vec(R_k - I, k = 1..K-1)     pose blend
    G_k      = G_parent(k) [R_k | J_k - J_parent(k)]              kinematic chain (kintree_table)
    v        = sum_k w_k G_k [I | -J_k] v_posed + trans           linear blend skinning

R_k is the rotation of joint k's axis-angle pose; vec flattens each 3x3 matrix row by row, joint
after joint, the order `posedirs` was learned in. Rotations act on column vectors. The rotations,
the chain and the skinning are `nmjax.geometry`'s NumPy twins.

Model files are read as their owners ship them (`load_model`): the official `.pkl` files (SMPL
1.1.0 for Python, MANO 1.2 `MANO_RIGHT.pkl`; Python 2 pickles whose arrays are partly chumpy
objects and whose `J_regressor` is a scipy sparse matrix) and `.npz` conversions with the same
keys. chumpy does not import on current NumPy, and unpickling may run code, so `.pkl` files go
through `restricted_load` (`nmjax.data.restricted_pickle` with this module's allow-list): it
rebuilds NumPy arrays, dtypes and scalars, scipy's compressed sparse matrices and chumpy arrays
(as the NumPy array they hold) and refuses every other class, naming it. The same reader opens
other array pickles (AIST++ motion files).
"""

from __future__ import annotations

import dataclasses
import os
import pickle
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from nmjax import geometry
from nmjax.data.restricted_pickle import RefusedGlobal, RestrictedUnpickler
from nmjax.parents import parents_from_external

# Joint counts of the two models; a file with another count is neither.
SMPL_JOINTS = 24
MANO_JOINTS = 16
MODEL_KINDS = {SMPL_JOINTS: "SMPL", MANO_JOINTS: "MANO"}
MANO_FINGER_POSE = 45  # 15 finger joints x 3 axis-angle values; `hands_mean` has this length

SMPL_JOINT_NAMES = (
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hand",
    "right_hand",
)

MODEL_KEYS = ("v_template", "shapedirs", "posedirs", "J_regressor", "kintree_table", "weights", "f")


# --- what a model file's pickle may hold ---------------------------------------------------------


class _ChumpyArray:
    """What a pickled chumpy object becomes: its state, kept until `_plain` takes the array out.

    chumpy pickles an object as its class and its attribute dict; a plain array (`chumpy.ch.Ch`)
    keeps its value under "x". Nothing of chumpy's is imported or run.
    """

    source = "chumpy"

    def __new__(cls, *_args: Any) -> _ChumpyArray:
        return object.__new__(cls)

    def __setstate__(self, state: Any) -> None:
        if isinstance(state, tuple) and len(state) == 2:  # (dict, slots) form of some pickles
            state = state[0]
        self.state = state if isinstance(state, dict) else {}


class _SparseMatrix:
    """What a pickled scipy compressed sparse matrix becomes: its state (data, indices, indptr,
    shape), turned into a dense array by `_plain` with scipy's own constructor."""

    layout = "csc"

    def __new__(cls, *_args: Any) -> _SparseMatrix:
        return object.__new__(cls)

    def __setstate__(self, state: Any) -> None:
        self.state = state if isinstance(state, dict) else {}


class _CscMatrix(_SparseMatrix):
    layout = "csc"


class _CsrMatrix(_SparseMatrix):
    layout = "csr"


@dataclasses.dataclass(frozen=True)
class Unevaluated:
    """A chumpy object that stores no array (an expression such as a sum); `load_model` refuses it
    where the model needs an array."""

    source: str


def _empty_array(subtype: Any, shape: Any, typecode: Any) -> np.ndarray:
    # NumPy pickles an array as this call followed by `ndarray.__setstate__` with its bytes.
    if subtype is not np.ndarray:
        raise pickle.UnpicklingError(f"refused array subclass {subtype!r}")
    return np.ndarray.__new__(np.ndarray, shape, np.dtype(typecode))


def _as_bytes(data: Any) -> bytes:
    # A Python 2 byte string arrives as str when read with encoding="latin1".
    return data.encode("latin1") if isinstance(data, str) else bytes(data)


def _scalar(dtype: np.dtype, data: Any = None) -> Any:
    if dtype.hasobject:
        return data  # an object scalar pickles the object itself, already read by these rules
    return np.frombuffer(_as_bytes(data), dtype=dtype, count=1)[0]


def _from_buffer(buffer: Any, dtype: np.dtype, shape: Any, order: str) -> np.ndarray:
    if dtype.hasobject:
        raise pickle.UnpicklingError("refused an object array given as raw bytes")
    flat = np.frombuffer(_as_bytes(buffer), dtype=dtype).copy()
    return flat.reshape(shape, order="F" if order == "F" else "C")


def _latin1_encode(text: str, encoding: str = "utf-8") -> bytes:
    # How Python 3 pickles bytes at protocol 2: `_codecs.encode(text, "latin1")`.
    if not isinstance(text, str) or encoding.replace("-", "").lower() != "latin1":
        raise pickle.UnpicklingError(f"refused _codecs.encode with encoding {encoding!r}")
    return text.encode("latin1")


def _reconstructor(cls: Any, base: Any, state: Any) -> Any:
    # Protocols 0 and 1 build new-style objects with copyreg._reconstructor(cls, object, None).
    if base is not object or not (isinstance(cls, type) and issubclass(cls, _STAND_INS)):
        raise pickle.UnpicklingError(f"refused copyreg._reconstructor for {cls!r}")
    return cls.__new__(cls)


_STAND_INS = (_ChumpyArray, _SparseMatrix)
_NUMPY_CORE = ("numpy.core", "numpy._core")
_ALLOWED: dict[tuple[str, str], Any] = {
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
    **{(f"{core}.multiarray", "_reconstruct"): _empty_array for core in _NUMPY_CORE},
    **{(f"{core}.multiarray", "scalar"): _scalar for core in _NUMPY_CORE},
    **{(f"{core}.numeric", "_frombuffer"): _from_buffer for core in _NUMPY_CORE},
    ("_codecs", "encode"): _latin1_encode,
    ("copy_reg", "_reconstructor"): _reconstructor,
    ("copyreg", "_reconstructor"): _reconstructor,
    ("__builtin__", "object"): object,
    ("builtins", "object"): object,
    ("__builtin__", "set"): set,
    ("builtins", "set"): set,
    ("__builtin__", "frozenset"): frozenset,
    ("builtins", "frozenset"): frozenset,
    # scipy has moved its sparse classes between modules over the years; all hold the same state.
    **{
        (f"scipy.sparse.{module}", f"{layout}_{kind}"): stand_in
        for layout, stand_in in (("csc", _CscMatrix), ("csr", _CsrMatrix))
        for module in (layout, f"_{layout}", "compressed", "_compressed")
        for kind in ("matrix", "array")
    },
}
_chumpy_classes: dict[str, type] = {}


def _chumpy_class(module: str, name: str) -> type | None:
    """One inert stand-in per chumpy class (None for any other module); none of chumpy's code
    exists or runs here."""
    if module != "chumpy" and not module.startswith("chumpy."):
        return None
    source = f"{module}.{name}"
    if source not in _chumpy_classes:
        _chumpy_classes[source] = type(name, (_ChumpyArray,), {"source": source})
    return _chumpy_classes[source]


def _sparse_to_dense(matrix: _SparseMatrix) -> np.ndarray:
    import scipy.sparse

    state = matrix.state
    shape = state.get("_shape", state.get("shape"))
    parts = [state.get(key) for key in ("data", "indices", "indptr")]
    if shape is None or any(not isinstance(p, np.ndarray) for p in parts):
        raise ValueError(f"a sparse {matrix.layout} matrix without data/indices/indptr/shape")
    build = scipy.sparse.csc_matrix if matrix.layout == "csc" else scipy.sparse.csr_matrix
    return build(tuple(parts), shape=tuple(int(n) for n in shape)).toarray()


def _plain(obj: Any) -> Any:
    """The unpickled object with every stand-in replaced by a NumPy array (or `Unevaluated`)."""
    if isinstance(obj, _ChumpyArray):
        if "x" not in obj.state:
            return Unevaluated(obj.source)
        value = _plain(obj.state["x"])
        return value if isinstance(value, Unevaluated) else np.asarray(value)
    if isinstance(obj, _SparseMatrix):
        return _sparse_to_dense(obj)
    if isinstance(obj, dict):
        return {key: _plain(value) for key, value in obj.items()}
    if isinstance(obj, list | tuple):
        return type(obj)(_plain(value) for value in obj)
    return obj


def restricted_load(file: BinaryIO | bytes, where: str | os.PathLike) -> Any:
    """Unpickles NumPy arrays, dtypes and scalars, scipy sparse matrices (as dense arrays), chumpy
    arrays (as NumPy arrays) and plain Python containers; refuses any other class.

    Python 2 pickles (the SMPL / MANO model files) are read with encoding "latin1", which is how
    their arrays' byte strings come back as bytes.

    Args:
      file: an open binary file or the pickle's bytes.
      where: the file's name, for error messages.

    Raises:
      ValueError: one line naming `where` and, for a refused class, the class.
    """
    try:
        obj = RestrictedUnpickler(file, _ALLOWED, other=_chumpy_class, encoding="latin1").load()
    except RefusedGlobal as err:
        raise ValueError(
            f"{where}: holds a pickled {err}; refused, a model or motion file holds only arrays, "
            "and nmjax loads no other class from a pickle (it could run code)"
        ) from err
    except pickle.UnpicklingError as err:
        raise ValueError(f"{where}: not a readable pickle ({err})") from err
    except (EOFError, TypeError, ValueError, AttributeError, IndexError, KeyError) as err:
        raise ValueError(f"{where}: not a readable pickle ({type(err).__name__}: {err})") from err
    try:
        return _plain(obj)
    except ValueError as err:
        raise ValueError(f"{where}: {err}") from err


# --- the model file ------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class BodyModel:
    """A SMPL-family model as NumPy arrays (float64), with V vertices, K joints, B shape betas.

    Attributes:
      v_template: (V, 3) rest-pose vertices of the mean shape.
      shapedirs: (V, 3, B) shape blend shapes.
      posedirs: (V, 3, 9 (K - 1)) pose blend shapes.
      j_regressor: (K, V) joints from vertices.
      parents: (K,) int parent of each joint, the root its own parent (from `kintree_table`).
      weights: (V, K) skinning weights.
      faces: (F, 3) int triangles.
      hands_mean: (45,) MANO's mean finger pose, or None (SMPL).
      path: the model file.
    """

    v_template: np.ndarray
    shapedirs: np.ndarray
    posedirs: np.ndarray
    j_regressor: np.ndarray
    parents: np.ndarray
    weights: np.ndarray
    faces: np.ndarray
    hands_mean: np.ndarray | None
    path: Path

    @property
    def num_joints(self) -> int:
        return int(self.parents.shape[0])

    @property
    def kind(self) -> str:
        """ "SMPL" (24 joints), "MANO" (16 joints), or a description of another joint count."""
        return MODEL_KINDS.get(self.num_joints, f"a {self.num_joints}-joint model")


def parents_from_kintree(kintree_table: np.ndarray, source: str = "kintree_table") -> np.ndarray:
    """(K,) parent index of each joint from SMPL's (2, K) `kintree_table`, the root its own parent.

    Row 1 holds the joint ids (a permutation of 0..K-1, the index used by `weights`, `J_regressor`
    and the pose vector), row 0 each one's parent id; the root's parent is -1, which the official
    files store as 2**32 - 1, or the root's own id (`nmjax.parents.parents_from_external`).

    Args:
      source: where the table comes from, named in errors (e.g. "MANO_RIGHT.pkl `kintree_table`").

    Raises:
      ValueError: ids that are not 0..K-1, an id past the end, not exactly one root, or a cycle.
    """
    table = np.asarray(kintree_table).astype(np.int64)
    if table.ndim != 2 or table.shape[0] != 2 or table.shape[1] < 1:
        raise ValueError(f"{source} must have shape (2, K), got {table.shape}")
    ids, parent_ids = table[1], table[0]
    num = ids.shape[0]
    if sorted(ids.tolist()) != list(range(num)):
        raise ValueError(f"{source} row 1 must list the joint ids 0..K-1")
    by_id = np.empty(num, dtype=np.int64)
    by_id[ids] = parent_ids
    return parents_from_external(by_id, source)


def chain_order(parents: np.ndarray) -> list[int]:
    """Joint indices ordered so that every parent comes before its children (the root, its own
    parent, first).

    Raises:
      ValueError: the parents do not form a tree (a cycle, or a parent out of range).
    """
    from nmjax.skeleton import skeleton_from_parents

    return list(skeleton_from_parents(np.asarray(parents)).order)


def _read_arrays(path: Path) -> dict[str, Any]:
    if path.suffix.lower() == ".npz":
        try:
            with np.load(path, allow_pickle=False) as archive:
                return {key: archive[key] for key in archive.files}
        except (OSError, ValueError, EOFError) as err:
            raise ValueError(f"{path}: not a readable .npz of arrays ({err})") from err
    if path.suffix.lower() == ".pkl":
        with open(path, "rb") as f:
            content = restricted_load(f, path)
        if not isinstance(content, dict):
            raise ValueError(f"{path}: expected a pickled dict of arrays, got {type(content)}")
        return content
    raise ValueError(f"{path}: a body model is a .pkl (as downloaded) or .npz file")


def _array(content: dict[str, Any], key: str, path: Path, ndim: int, dtype: type) -> np.ndarray:
    value = content.get(key)
    if value is None:
        raise ValueError(f"{path}: no {key!r} array; is this a SMPL / MANO model file?")
    if isinstance(value, Unevaluated):
        raise ValueError(f"{path}: {key!r} is a chumpy expression ({value.source}), not an array")
    try:
        array = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{path}: {key!r} is not a numeric array ({err})") from err
    if array.ndim != ndim:
        raise ValueError(f"{path}: {key!r} must have {ndim} dimensions, got shape {array.shape}")
    if dtype is np.float64 and not np.isfinite(array).all():
        raise ValueError(f"{path}: {key!r} contains NaN or inf")
    return array


def load_model(path: str | os.PathLike) -> BodyModel:
    """Reads a SMPL or MANO model file (official `.pkl` or a `.npz` with the same keys).

    Keys read: v_template, shapedirs, posedirs, J_regressor (dense or sparse), kintree_table,
    weights, f, and hands_mean where present (MANO). Every shape is checked against V and K.

    Raises:
      FileNotFoundError: no file at `path`.
      ValueError: one line naming the file and what is wrong with it.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"--body-model {path}: no such file")
    content = _read_arrays(path)
    v_template = _array(content, "v_template", path, 2, np.float64)
    num_vertices = v_template.shape[0]
    table = _array(content, "kintree_table", path, 2, np.int64)
    parents = parents_from_kintree(table, f"{path} `kintree_table`")
    num_joints = parents.shape[0]
    shapedirs = _array(content, "shapedirs", path, 3, np.float64)
    posedirs = _array(content, "posedirs", path, 3, np.float64)
    expected = {
        "v_template": ((num_vertices, 3), v_template.shape),
        "shapedirs": ((num_vertices, 3, shapedirs.shape[2]), shapedirs.shape),
        "posedirs": ((num_vertices, 3, 9 * (num_joints - 1)), posedirs.shape),
    }
    j_regressor = _array(content, "J_regressor", path, 2, np.float64)
    weights = _array(content, "weights", path, 2, np.float64)
    faces = _array(content, "f", path, 2, np.int64)
    expected |= {
        "J_regressor": ((num_joints, num_vertices), j_regressor.shape),
        "weights": ((num_vertices, num_joints), weights.shape),
        "f": ((faces.shape[0], 3), faces.shape),
    }
    for key, (want, got) in expected.items():
        if want != got:
            raise ValueError(
                f"{path}: {key!r} has shape {got}, expected {want} for {num_vertices} vertices "
                f"and {num_joints} joints"
            )
    if faces.size and (faces.min() < 0 or faces.max() >= num_vertices):
        raise ValueError(f"{path}: 'f' indexes vertices outside 0..{num_vertices - 1}")
    hands_mean = None
    if content.get("hands_mean") is not None:
        hands_mean = _array(content, "hands_mean", path, 1, np.float64)
        if hands_mean.shape != (3 * (num_joints - 1),):
            raise ValueError(
                f"{path}: 'hands_mean' has shape {hands_mean.shape}, expected "
                f"({3 * (num_joints - 1)},)"
            )
    return BodyModel(
        v_template=v_template,
        shapedirs=shapedirs,
        posedirs=posedirs,
        j_regressor=j_regressor,
        parents=parents,
        weights=weights,
        faces=faces,
        hands_mean=hands_mean,
        path=path,
    )


def require_kind(model: BodyModel, kind: str, user: str, where_to_get: str) -> None:
    """Refuses `model` unless it is `kind` ("SMPL" or "MANO", told apart by their joint counts).

    Raises:
      ValueError: one line naming the file, what it is, what `user` needs and where to get it.
    """
    if model.kind != kind:
        joints = {name: count for count, name in MODEL_KINDS.items()}[kind]
        raise ValueError(
            f"--body-model {model.path}: {model.kind} ({model.num_joints} joints), but {user} "
            f"needs {kind} ({joints} joints): {where_to_get}"
        )


# --- the forward pass ----------------------------------------------------------------------------


def shape_blend(v_template: np.ndarray, shapedirs: np.ndarray, betas: np.ndarray) -> np.ndarray:
    """Rest-pose vertices of shape `betas`: v_template + shapedirs . betas.

    Args:
      v_template: (V, 3).
      shapedirs: (V, 3, B).
      betas: (..., B') with B' <= B; the missing trailing betas are zero.

    Returns:
      (..., V, 3).
    """
    betas = np.asarray(betas, dtype=np.float64)
    count = betas.shape[-1]
    if count > shapedirs.shape[-1]:
        raise ValueError(f"{count} betas given, the model has {shapedirs.shape[-1]}")
    # As one matrix product (BLAS): (..., B') @ (B', 3V).
    offsets = betas @ shapedirs[..., :count].reshape(-1, count).T
    return v_template + offsets.reshape(*betas.shape[:-1], *v_template.shape)


def regress_joints(j_regressor: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Joints as fixed combinations of vertices: (K, V) and (..., V, 3) -> (..., K, 3)."""
    return j_regressor @ vertices


def pose_blend(posedirs: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """Pose-dependent vertex offsets: posedirs . vec(R_k - I) over the non-root joints.

    Zero at the rest pose (every R_k = I).

    Args:
      posedirs: (V, 3, 9 (K - 1)).
      rotations: (..., K, 3, 3); joint 0 (the root) does not enter.

    Returns:
      (..., V, 3).
    """
    features = rotations[..., 1:, :, :] - np.eye(3)
    features = features.reshape(*rotations.shape[:-3], -1)
    # As one matrix product (BLAS): (..., 9 (K - 1)) @ (9 (K - 1), 3V).
    offsets = features @ posedirs.reshape(-1, posedirs.shape[-1]).T
    return offsets.reshape(*features.shape[:-1], *posedirs.shape[:2])


def pose_model(
    model: BodyModel,
    pose: np.ndarray,
    betas: np.ndarray | None = None,
    trans: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Posed vertices and joints of `model` (the forward pass in the module docstring).

    Args:
      model: a loaded `BodyModel` with K joints.
      pose: (..., 3 K) axis-angle per joint, root first (joint order of `kintree_table` ids).
        MANO's mean hand pose is not added here; see `mano_pose`.
      betas: (..., B') shape coefficients, or None for the mean shape.
      trans: (..., 3) translation added to every vertex and joint, or None.

    Returns:
      (vertices (..., V, 3), joints (..., K, 3)): the skinned vertices and the chain's posed joint
      positions, both translated.
    """
    pose = np.asarray(pose, dtype=np.float64)
    num = model.num_joints
    if pose.shape[-1] != 3 * num:
        raise ValueError(f"{model.kind} takes {3 * num} pose values per frame, got {pose.shape}")
    batch = pose.shape[:-1]
    rotations = geometry.axis_angle_to_matrix_np(pose.reshape(*batch, num, 3))
    if betas is None:
        shaped = np.broadcast_to(model.v_template, (*batch, *model.v_template.shape))
    else:
        shaped = shape_blend(model.v_template, model.shapedirs, betas)
        shaped = np.broadcast_to(shaped, (*batch, *model.v_template.shape))
    rest_joints = regress_joints(model.j_regressor, shaped)
    posed_rest = shaped + pose_blend(model.posedirs, rotations)
    # G_k = G_parent(k) [R_k | J_k - J_parent(k)]: each bone turned by its parent's frame.
    order = chain_order(model.parents)
    bones = rest_joints - rest_joints[..., model.parents, :]  # the root's (zero) is not used
    joints, world = geometry.forward_kinematics_np(
        rest_joints[..., order[0], :], rotations, bones, model.parents, order, offset_frame="parent"
    )
    # G_k [I | -J_k] keeps G_k's rotation and moves its translation by -R_k J_k.
    translations = joints - (world @ rest_joints[..., None])[..., 0]
    vertices = geometry.linear_blend_skinning_np(posed_rest, model.weights, world, translations)
    if trans is not None:
        trans = np.asarray(trans, dtype=np.float64)[..., None, :]
        vertices, joints = vertices + trans, joints + trans
    return vertices, joints


def mano_pose(model: BodyModel, pose: np.ndarray) -> np.ndarray:
    """MANO's full pose from a pose stored relative to its mean hand: the root's 3 values as given,
    `hands_mean` added to the 45 finger values (so a stored zero pose is the relaxed mean hand,
    not the flat hand).

    Args:
      model: a MANO model (with `hands_mean`).
      pose: (..., 48).

    Returns:
      (..., 48), ready for `pose_model`.
    """
    if model.hands_mean is None:
        raise ValueError(f"{model.path}: no 'hands_mean' array; MANO_RIGHT.pkl holds one")
    pose = np.array(pose, dtype=np.float64)
    pose[..., 3:] += model.hands_mean
    return pose
