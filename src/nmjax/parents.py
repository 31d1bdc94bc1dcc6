"""Parent arrays that come from outside nmjax, read into its one convention.

Inside nmjax a tree over K joints is a (K,) parent array whose root is its own parent
(`nmjax.skeleton.skeleton_from_parents`). Files mark the root otherwise; every reader of a parent
array from a file or an option (a dataset's meta.json, `nmjax.data.layout.read_meta_file`; a
body model's kintree_table, `nmjax.data.body_models`; skeleton.json, `nmjax.skeleton`) calls
`parents_from_external` where the values come in. NumPy only, so that the data layer can use it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

# SMPL's kintree_table stores the root's missing parent as -1 in an unsigned 32-bit integer.
UINT32_MINUS_ONE = 2**32 - 1


def parents_from_external(values: Any, source: str) -> np.ndarray:
    """A parent array read from outside the library, in the library's convention: the root is
    its own parent (what `skeleton_from_parents` and every tree inside nmjax take).

    Trees come with their root marked in one of three ways, all accepted: a negative parent (-1
    in BVH tools, most datasets and SMPL / MANO's `kintree_table` as signed integers), 2**32 - 1
    (that -1 read as an unsigned 32-bit integer, as the official `.pkl` files hold it), or the
    root's own index. Every reader of a parent array from a file or an option calls this once,
    where the values come in.

    Args:
      values: (K,) integers: a list read from JSON or an array of any integer dtype.
      source: where the values come from, named in every error, e.g. "data/x/meta.json
        `parents`".

    Returns:
      (K,) int64 parents; the root's entry is its own index.

    Raises:
      ValueError: one line naming `source` and the bad entry: not a non-empty list of integers,
        an index past the last joint, no root or more than one, a cycle.
    """
    raw = np.asarray(values)
    if raw.ndim != 1 or raw.size == 0 or not np.issubdtype(raw.dtype, np.integer):
        raise ValueError(f"{source}: expected a non-empty list of integer parent indices")
    if raw.dtype == np.uint64:  # wraps 2**64 - 1 to -1, which is a root like any negative
        raw = raw.view(np.int64)
    raw = raw.astype(np.int64)
    num = raw.size
    index = np.arange(num)
    root = (raw < 0) | (raw == UINT32_MINUS_ONE) | (raw == index)
    past = np.flatnonzero(~root & (raw >= num))
    if past.size:
        k = int(past[0])
        raise ValueError(
            f"{source}: entry {k} names parent {int(raw[k])}, past the last joint {num - 1}; "
            "give the root as -1 or as its own index"
        )
    roots = np.flatnonzero(root)
    if roots.size != 1:
        found = "no root" if roots.size == 0 else f"{roots.size} roots (entries {roots.tolist()})"
        raise ValueError(
            f"{source}: a tree has exactly one root (-1 or its own index), found {found} in "
            f"{raw.tolist()}"
        )
    parents = np.where(root, index, raw)
    reached, frontier = {int(roots[0])}, [int(roots[0])]
    while frontier:  # down from the root: whatever it does not reach hangs off a cycle
        frontier = [int(k) for k in np.flatnonzero(np.isin(parents, frontier)) if k not in reached]
        reached.update(frontier)
    if len(reached) != num:
        stray = sorted(set(range(num)) - reached)
        raise ValueError(
            f"{source}: entries {stray} never reach the root {int(roots[0])} (their parents form "
            f"a cycle) in {raw.tolist()}"
        )
    return parents
