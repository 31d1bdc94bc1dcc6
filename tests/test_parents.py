"""Parent arrays from outside the library (nmjax.parents.parents_from_external): a root given as
-1 (any negative), as 2**32 - 1 or as its own index is accepted by every reader of a tree from a
file, and comes out as its own parent; a cycle, two roots or an index past the end are refused in
one line naming the file and the entry."""

from __future__ import annotations

import json
import types
from pathlib import Path

import numpy as np
import pytest
import trimesh
from body_model_files import chain_model, write_npz

from nmjax import evaluate, skeleton
from nmjax.data import body_models, layout, prepare
from nmjax.parents import parents_from_external

TREE = [0, 0, 1, 1]  # nmjax's convention: the root is its own parent
ROOTS = {"minus one": -1, "any negative": -7, "uint32 minus one": 2**32 - 1, "own index": 0}
CYCLE = [-1, 2, 1, 1]  # 1 and 2 each other's parent, 3 hangs off them
TWO_ROOTS = [-1, 0, 2, 1]


def with_root(root: int) -> list[int]:
    return [root, *TREE[1:]]


def test_every_root_convention_becomes_the_roots_own_index():
    for root in ROOTS.values():
        got = parents_from_external(with_root(root), "test")
        assert got.dtype == np.int64 and got.tolist() == TREE
    for dtype in (np.uint32, np.int32, np.uint64, np.int64):  # as arrays of any integer type
        values = np.array(with_root(-1)).astype(dtype)
        assert parents_from_external(values, "test").tolist() == TREE
    # A root that is not joint 0, marked each way.
    for root in (-1, 2**32 - 1, 2):
        assert parents_from_external([2, 0, root], "x").tolist() == [2, 0, 2]


@pytest.mark.parametrize(
    "values, match",
    [
        (CYCLE, r"x.json `parents`: entries \[1, 2, 3\] never reach the root 0"),
        (TWO_ROOTS, r"x.json `parents`: .*exactly one root.*found 2 roots \(entries \[0, 2\]\)"),
        ([1, 2, 0], r"found no root"),
        ([-1, 0, 9], r"x.json `parents`: entry 2 names parent 9, past the last joint 2"),
        ([], r"non-empty list of integer"),
        ([-1.0, 0.0], r"non-empty list of integer"),
        ([[-1, 0]], r"non-empty list of integer"),
    ],
)
def test_what_is_not_a_tree_is_one_line_naming_the_source_and_entry(values, match):
    with pytest.raises(ValueError, match=match) as refused:
        parents_from_external(values, "x.json `parents`")
    assert "\n" not in str(refused.value)


# --- every reader of a tree from a file -------------------------------------------------------


def read_dataset_meta(folder: Path, parents: list[int]) -> tuple[list[int], Path]:
    """A dataset's meta.json, read by `layout.read_meta` (evaluation, the viewer)."""
    (folder / "meta.json").write_text(json.dumps({"parents": parents, "sample_rate": 1}))
    return layout.read_meta("synth-arm", folder)["parents"], folder / "meta.json"


def read_true_tree(folder: Path, parents: list[int]) -> tuple[list[int], Path]:
    """`nmjax evaluate`'s true tree, from the meta.json of the detector's dataset."""
    (folder / "meta.json").write_text(json.dumps({"parents": parents}))
    data = types.SimpleNamespace(name="synth-arm", root=str(folder))
    detector = types.SimpleNamespace(cfg=types.SimpleNamespace(data=data))
    return evaluate.true_tree(detector, len(parents)).tolist(), folder / "meta.json"


def read_prepared_source(folder: Path, parents: list[int]) -> tuple[list[int], Path]:
    """`nmjax prepare-data` from mesh folders whose meta.json gives the tree: the prepared set's
    meta.json holds it in nmjax's convention."""
    source, root = folder / "raw", folder / "out"
    for seq in ("walk", "run"):
        (source / seq).mkdir(parents=True)
        for t in range(2):
            trimesh.creation.box().export(source / seq / f"frame_{t}.obj")
    (source / "meta.json").write_text(json.dumps({"parents": parents}))
    prepare.prepare_real("dfaust", source, root, points=50)
    return json.loads((root / "meta.json").read_text())["parents"], source / "meta.json"


def read_body_model(folder: Path, parents: list[int]) -> tuple[list[int], Path]:
    """A SMPL-family model's kintree_table (row 0 the parents, row 1 the joint ids)."""
    arrays = chain_model()
    num = len(parents)
    arrays["kintree_table"] = np.array([parents, list(range(num))], dtype=np.int64)
    for key in ("J_regressor", "weights"):  # K joints: more rows or columns of the chain's
        arrays[key] = np.resize(arrays[key], (num, 7) if key == "J_regressor" else (7, num))
    arrays["posedirs"] = np.zeros((7, 3, 9 * (num - 1)))
    path = write_npz(folder / "model.npz", arrays)
    return body_models.load_model(path).parents.tolist(), path


def read_skeleton_file(folder: Path, parents: list[int]) -> tuple[list[int], Path]:
    """A run's skeleton.json (the tree of `nmjax extract-skeleton`, or one written by hand)."""
    (folder / "skeleton.json").write_text(json.dumps({"parents": parents}))
    return list(skeleton.load_skeleton(folder / "skeleton.json").parents), folder / "skeleton.json"


READERS = [read_dataset_meta, read_true_tree, read_prepared_source, read_body_model]
READERS.append(read_skeleton_file)


@pytest.mark.parametrize("reader", READERS, ids=lambda f: f.__name__)
@pytest.mark.parametrize("root", ROOTS.values(), ids=ROOTS.keys())
def test_every_reader_accepts_each_root_convention(reader, root, tmp_path):
    parents, _ = reader(tmp_path, with_root(root))
    assert parents == TREE


@pytest.mark.parametrize("reader", READERS, ids=lambda f: f.__name__)
@pytest.mark.parametrize("values, what", [(CYCLE, "never reach the root"), (TWO_ROOTS, "2 roots")])
def test_every_reader_refuses_a_cycle_and_two_roots_naming_the_file(reader, values, what, tmp_path):
    with pytest.raises(ValueError) as refused:
        reader(tmp_path, values)
    message = str(refused.value)
    assert what in message and "\n" not in message, message
    assert message.startswith(str(tmp_path)), message  # the file, then what is wrong with it
