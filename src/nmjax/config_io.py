"""Reading and writing a configuration: config.json both ways (its older layouts included,
`migrate`) and the command line's `--set FIELD=VALUE` overrides, for any of `nmjax.config`'s
dataclasses.

Generic over the dataclass it is given, so it imports none of them: `nmjax.config` builds its
presets with `replace_paths` / `replace_fields` from here, and a dataclass names the fields it
moved itself (`MOVED_FIELDS`).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from typing import Any

# The groups both train configurations hold. Their fields were top-level fields of the train
# configurations before they were grouped: a config.json of that time (flat) is read into them
# (`migrate`), and `--set NAME=VALUE` / `replace_fields` still take the bare names.
SHARED_GROUPS = ("optim", "loop")
# The class attribute in which a configuration dataclass lists the top-level fields it moved into
# a group since: {old name: dotted field today} (`nmjax.config.DynTrainConfig`'s, phase 2's data
# before it was a group). Read by `migrate`, and by `--set` / `replace_fields` for the old names.
MOVED_FIELDS = "MOVED_FIELDS"


# --- reading and writing a configuration (config.json) -----------------------------------------


def config_to_dict(config: Any) -> dict[str, Any]:
    """`dataclasses.asdict`, with tuples turned into lists so that it round-trips through JSON."""
    return json.loads(json.dumps(dataclasses.asdict(config)))


def flatten_config(config: Any) -> dict[str, Any]:
    """{dotted field: value} of a configuration (a dataclass, or its `config_to_dict` form), as
    `config_to_dict` writes the values (the names that `--set` and the resume and fine-tuning
    checks use)."""

    def walk(tree: Mapping[str, Any], prefix: str) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for key, value in tree.items():
            if isinstance(value, Mapping):
                out.update(walk(value, f"{prefix}{key}."))
            else:
                out[f"{prefix}{key}"] = value
        return out

    return walk(config if isinstance(config, Mapping) else config_to_dict(config), "")


def config_from_dict(
    cls: type, data: Mapping[str, Any], *, source: str = "config", base: Any = None
) -> Any:
    """Rebuilds the (nested, frozen) dataclass `cls` from `config_to_dict` output, of today's
    layout or an older one (`migrate`).

    A key missing from `data` takes its value in `base` (default: the dataclass default), and so
    does a missing key of a nested group: a phase's groups have the phase's defaults (phase 2's
    `loop.epochs` is 150 where phase 1's is 200). Unknown keys are refused so that a stale config
    file is noticed.
    """
    data = migrate(cls, data)
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(
            f"{source}: unknown field(s) {unknown} for {cls.__name__}; "
            f"valid fields: {sorted(names)}"
        )
    base = cls() if base is None else base
    kwargs = {}
    for name, value in data.items():
        where = f"{source}.{name}"
        hint = hints[name]
        if dataclasses.is_dataclass(hint) and isinstance(hint, type):
            if not isinstance(value, Mapping):
                raise ValueError(f"{where}: expected a mapping for {hint.__name__}, got {value!r}")
            kwargs[name] = config_from_dict(hint, value, source=where, base=getattr(base, name))
        else:
            kwargs[name] = _convert(hint, value)
    return dataclasses.replace(base, **kwargs)


# --- older layouts of config.json ---------------------------------------------------------------


def migrate(cls: type, data: Mapping[str, Any]) -> dict[str, Any]:
    """`data`, a config.json of the dataclass `cls` in any layout it has had, in today's.

    The layouts, oldest first; each step reads the one before it into the next:

    1. flat: every field of the shared groups at the top level (`steps`, `learning_rate`, ...);
       `_nest_shared_fields` moves them into `optim` and `loop` (`SHARED_GROUPS`).
    2. grouped, but phase 2's `data` the dataset's name, with `frames`, `batch_size` and `inputs`
       beside it at the top; `_nest_moved_fields` moves them into the `data` group
       (`MOVED_FIELDS` of the class).
    3. today's: `data` a group in both phases.

    No config.json records its layout: each step recognises the keys it moves by where they
    are, and leaves a file of a later layout as it is.
    """
    for step in (_nest_shared_fields, _nest_moved_fields):
        data = step(cls, data)
    return dict(data)


def _group_of(cls: type, name: str) -> str | None:
    """The shared group (`SHARED_GROUPS`) of `cls` that has a field `name`, if any."""
    hints = typing.get_type_hints(cls)
    for group in SHARED_GROUPS:
        if group in hints and name in _field_names(hints[group]):
            return group
    return None


def _nest_shared_fields(cls: type, data: Mapping[str, Any]) -> dict[str, Any]:
    """`data` with every top-level key that names a field of one of `cls`'s shared groups moved
    into that group (layout 1 of `migrate`)."""
    if not dataclasses.is_dataclass(cls) or not any(
        f.name in SHARED_GROUPS for f in dataclasses.fields(cls)
    ):
        return dict(data)
    own = {f.name for f in dataclasses.fields(cls)}
    out: dict[str, Any] = {}
    for key, value in data.items():
        group = None if key in own else _group_of(cls, key)
        if group is None:
            out[key] = value
        else:
            out.setdefault(group, {})
            out[group] = {**out[group], key: value}
    return out


def _moved_fields(cls: type) -> Mapping[str, str]:
    return getattr(cls, MOVED_FIELDS, {})


def _is_old_spelling(cls: type, name: str, is_group_value: bool) -> bool:
    """Whether `name` with a value that is (or is not) a group is a field `cls` moved: a name it
    no longer has at the top, or a name that is a group now given a plain value (phase 2's
    `data` as a dataset name)."""
    if name not in _moved_fields(cls):
        return False
    if name not in _field_names(cls):
        return True
    return _is_group(cls, name) and not is_group_value


def _is_group(cls: type, name: str) -> bool:
    hint = typing.get_type_hints(cls)[name]
    return dataclasses.is_dataclass(hint) and isinstance(hint, type)


def _nest_moved_fields(cls: type, data: Mapping[str, Any]) -> dict[str, Any]:
    """`data` with every top-level key that `cls` moved into a group since (`MOVED_FIELDS`) put
    where it lives today (layout 2 of `migrate`)."""
    if not dataclasses.is_dataclass(cls):
        return dict(data)
    out: dict[str, Any] = {}
    moved: dict[str, Any] = {}
    for key, value in data.items():
        if _is_old_spelling(cls, key, isinstance(value, Mapping)):
            moved[_moved_fields(cls)[key]] = value
        else:
            out[key] = value
    for path, value in moved.items():
        *groups, leaf = path.split(".")
        node = out
        for group in groups:
            node[group] = dict(node.get(group, {}))
            node = node[group]
        node[leaf] = value
    return out


def _convert(hint: Any, value: Any) -> Any:
    origin = typing.get_origin(hint)
    if origin is tuple and isinstance(value, list | tuple):
        return tuple(value)
    if origin in (typing.Union, types.UnionType) and isinstance(value, list):
        return tuple(value)
    return value


# --- command-line overrides (`--set FIELD=VALUE`) --------------------------------------------


def _parse_value(text: str, key: str, current: Any) -> Any:
    """`text` (a `--set` value) read as the type of the field's `current` value."""
    if isinstance(current, bool):
        if text.lower() in ("1", "true", "yes"):
            return True
        if text.lower() in ("0", "false", "no"):
            return False
        raise ValueError(f"--set {key}: expected true/false, got {text!r}")
    if isinstance(current, tuple):
        parts = [p for p in text.strip("()[] ").split(",") if p.strip()]
        kind = type(current[0]) if current else float
        return tuple(kind(p) for p in parts)
    if current is None:
        return None if text.lower() == "none" else text
    try:
        return type(current)(text) if not isinstance(current, int) else int(text)
    except ValueError:
        raise ValueError(f"--set {key}: cannot read {text!r} as {type(current).__name__}") from None


def add_override_argument(parser: argparse.ArgumentParser, help: str) -> None:
    """Adds the repeatable `--set FIELD=VALUE` option read by `apply_overrides`."""
    parser.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="FIELD=VALUE", help=help
    )


def apply_overrides(cfg: Any, assignments: Sequence[str]) -> Any:
    """Returns `cfg` with dotted-path overrides like "model.channels=16" or "lr_decay=0.5,0.1"
    (a shared group's field by its bare name, `SHARED_GROUPS`, or dotted: "optim.lr_decay"; a
    moved field by its old name, `MOVED_FIELDS`: phase 2's "batch_size" for "data.batch_size")."""
    for item in assignments:
        if "=" not in item:
            raise ValueError(f"--set expects FIELD=VALUE (e.g. model.channels=16), got {item!r}")
        key, text = item.split("=", 1)
        path = _field_path(cfg, key.strip().split("."), is_group_value=False)
        cfg = _replace_path(cfg, path, functools.partial(_parse_value, text.strip(), key), key)
    return cfg


def replace_paths(cfg: Any, changes: Mapping[str, Any]) -> Any:
    """`cfg` with the values of {dotted field: value} set (`"data.grid": 32`): the programmatic
    form of `apply_overrides`, with values instead of texts (the presets' tables)."""
    for key, value in changes.items():
        whole = dataclasses.is_dataclass(value)
        path = _field_path(cfg, key.split("."), whole)
        cfg = _replace_path(cfg, path, functools.partial(_given, value), key, whole)
    return cfg


def _given(value: Any, _current: Any) -> Any:
    return value


def replace_fields(cfg: Any, **changes: Any) -> Any:
    """`dataclasses.replace(cfg, ...)` that also takes the shared groups' fields by their bare
    names (`steps=4, learning_rate=1e-3` for `loop.steps`, `optim.learning_rate`) and the moved
    fields by their old names (phase 2's `batch_size=8` for `data.batch_size`), as `--set` does."""
    return replace_paths(cfg, changes)


def _field_names(obj: Any) -> set[str]:
    return {f.name for f in dataclasses.fields(obj)}


def _field_path(obj: Any, path: list[str], is_group_value: bool) -> list[str]:
    """`path` (a key split at its dots) as it is spelled today: a moved field's old name is its
    path now (`MOVED_FIELDS`), a shared group's field by its bare name gets the group in front."""
    if len(path) == 1 and _is_old_spelling(type(obj), path[0], is_group_value):
        return _moved_fields(type(obj))[path[0]].split(".")
    if path[0] not in _field_names(obj) and (group := _group_of(type(obj), path[0])) is not None:
        return [group, *path]
    return path


def _replace_path(
    obj: Any, path: list[str], leaf: Callable[[Any], Any], key: str, whole_group: bool = False
) -> Any:
    """`obj` with the field at `path` set to `leaf(its current value)`; a group is replaced
    whole only when `whole_group` (a dataclass given as the value)."""
    names = _field_names(obj)
    if path[0] not in names:
        raise ValueError(
            f"--set {key}: {type(obj).__name__} has no field {path[0]!r}; fields: {sorted(names)}"
        )
    current = getattr(obj, path[0])
    if len(path) == 1:
        if dataclasses.is_dataclass(current) and not whole_group:
            raise ValueError(f"--set {key}: {path[0]} is a group; set one of its fields")
        value = leaf(current)
    else:
        if not dataclasses.is_dataclass(current):
            raise ValueError(f"--set {key}: {path[0]} has no sub-fields")
        value = _replace_path(current, path[1:], leaf, key, whole_group)
    return dataclasses.replace(obj, **{path[0]: value})
