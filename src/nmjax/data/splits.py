"""The published train/test splits behind the paper's tables, shipped with the package.

    split_lists/<name>_train.txt, <name>_test.txt   one name a line (split_lists/README.md)

AIST++ (`aist`) lists sequences; D-FAUST (`dfaust`) lists subject ids, and a registration
`<subject>_<motion>` follows its subject; DeformingThings4D animals (`animals`) lists species, and
a sequence `<object>_<action>` follows the species its object id starts with (`bear3EP_Agression`
is a bear; the longest match wins, so `cattle...` is cattle and not cat). Every other set has no
list and is split 9:1 by frames (`nmjax.data.layout.split_by_frames`), as the paper does for HanCo
and Panda.
"""

from __future__ import annotations

import functools
from collections.abc import Collection, Iterable
from importlib import resources

from nmjax.data.layout import SPLITS

PUBLISHED_SPLITS: dict[str, str] = {"aist": "sequence", "dfaust": "subject", "animals": "species"}


@functools.cache
def read_published(name: str) -> dict[str, tuple[str, ...]]:
    """The published lists of dataset `name`: {"train": names, "test": names} as shipped.

    Raises:
      ValueError: `name` has no published split, or a name is in both lists.
    """
    if name not in PUBLISHED_SPLITS:
        raise ValueError(
            f"dataset {name!r} has no published split (those with one: "
            f"{', '.join(PUBLISHED_SPLITS)}); it is split 9:1 by frames"
        )
    folder = resources.files("nmjax.data").joinpath("split_lists")
    lists = {}
    for split in SPLITS:
        text = folder.joinpath(f"{name}_{split}.txt").read_text(encoding="utf-8")
        lists[split] = tuple(line.strip() for line in text.splitlines() if line.strip())
    both = set(lists["train"]) & set(lists["test"])
    if both:
        raise ValueError(f"published {name} split: {sorted(both)[:5]} in both train and test")
    return lists


def listed_as(name: str, seq: str, listed: Collection[str]) -> str | None:
    """The entry of the published lists of `name` that sequence `seq` falls under, or None.

    `listed` holds every entry of both lists (a set or a dict, for fast membership): sequence
    names (aist), subject ids (dfaust) or species (animals).
    """
    unit = PUBLISHED_SPLITS[name]
    if unit == "sequence":
        key = seq
    elif unit == "subject":
        key = seq.split("_", 1)[0]
    else:  # species: the object id (before the first "_") starts with the species name
        obj = seq.split("_", 1)[0]
        matches = [species for species in listed if obj.startswith(species)]
        return max(matches, key=len) if matches else None
    return key if key in listed else None


def published_split(name: str, sequences: Iterable[str]) -> tuple[dict[str, list[str]], list[str]]:
    """Divides `sequences` of dataset `name` by its published lists.

    Returns:
      ({"train": sorted names, "test": sorted names}, sorted names in neither list); the names
      in neither list are in no split.
    """
    lists = read_published(name)
    listed = {entry: split for split in SPLITS for entry in lists[split]}
    split: dict[str, list[str]] = {s: [] for s in SPLITS}
    left_out = []
    for seq in sorted(sequences):
        entry = listed_as(name, seq, listed)
        if entry is None:
            left_out.append(seq)
        else:
            split[listed[entry]].append(seq)
    return split, left_out
