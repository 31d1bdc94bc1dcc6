"""Reading and writing a configuration: config.json both ways (old flat layouts included) and
the command line's `--set FIELD=VALUE` overrides, for any of `nmjax.config`'s dataclasses.

Generic over the dataclass it is given, so it imports none of them: `nmjax.config` builds its
presets with `replace_fields` / `apply_overrides` from here.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import types
import typing
from collections.abc import Mapping, Sequence
from typing import Any

# The groups both train configurations hold. Their fields were top-level fields of the train
# configurations before they were grouped: a config.json of that time (flat) is read into them
# (`config_from_dict`), and `--set NAME=VALUE` / `replace_fields` still take the bare names.
SHARED_GROUPS = ("optim", "loop")


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
    """Rebuilds the (nested, frozen) dataclass `cls` from `config_to_dict` output.

    A key missing from `data` takes its value in `base` (default: the dataclass default), and so
    does a missing key of a nested group: a phase's groups have the phase's defaults (phase 2's
    `loop.epochs` is 150 where phase 1's is 200). A config.json written before the shared groups
    existed (`SHARED_GROUPS`: `steps`, `learning_rate`, ... at the top level) is read into them.
    Unknown keys are refused so that a stale config file is noticed.
    """
    data = _nest_shared_fields(cls, data)
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


def _group_of(cls: type, name: str) -> str | None:
    """The shared group (`SHARED_GROUPS`) of `cls` that has a field `name`, if any."""
    hints = typing.get_type_hints(cls)
    for group in SHARED_GROUPS:
        if group in hints and name in _field_names(hints[group]):
            return group
    return None


def _nest_shared_fields(cls: type, data: Mapping[str, Any]) -> dict[str, Any]:
    """`data` with every top-level key that names a field of one of `cls`'s shared groups moved
    into that group (the flat layout of older config.json files)."""
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


def _convert(hint: Any, value: Any) -> Any:
    origin = typing.get_origin(hint)
    if origin is tuple and isinstance(value, list | tuple):
        return tuple(value)
    if origin in (typing.Union, types.UnionType) and isinstance(value, list):
        return tuple(value)
    return value


# --- command-line overrides (`--set FIELD=VALUE`) --------------------------------------------


def _parse_value(text: str, current: Any, key: str) -> Any:
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
    (a shared group's field by its bare name, `SHARED_GROUPS`, or dotted: "optim.lr_decay")."""
    for item in assignments:
        if "=" not in item:
            raise ValueError(f"--set expects FIELD=VALUE (e.g. model.channels=16), got {item!r}")
        key, text = item.split("=", 1)
        cfg = _replace_path(cfg, key.strip().split("."), text.strip(), key)
    return cfg


def replace_fields(cfg: Any, **changes: Any) -> Any:
    """`dataclasses.replace(cfg, ...)` that also takes the shared groups' fields by their bare
    names (`steps=4, learning_rate=1e-3` for `loop.steps`, `optim.learning_rate`), as `--set`
    does: the programmatic form of `apply_overrides`, with values instead of texts."""
    for name, value in changes.items():
        group = _group_of(type(cfg), name) if name not in _field_names(cfg) else None
        if group is None:
            cfg = dataclasses.replace(cfg, **{name: value})
        else:
            inner = dataclasses.replace(getattr(cfg, group), **{name: value})
            cfg = dataclasses.replace(cfg, **{group: inner})
    return cfg


def _field_names(obj: Any) -> set[str]:
    return {f.name for f in dataclasses.fields(obj)}


def _replace_path(obj: Any, path: list[str], text: str, key: str) -> Any:
    names = _field_names(obj)
    if path[0] not in names and (group := _group_of(type(obj), path[0])) is not None:
        path = [group, *path]  # a shared group's field by its bare (pre-group) name
    if path[0] not in names:
        raise ValueError(
            f"--set {key}: {type(obj).__name__} has no field {path[0]!r}; fields: {sorted(names)}"
        )
    current = getattr(obj, path[0])
    if len(path) == 1:
        if dataclasses.is_dataclass(current):
            raise ValueError(f"--set {key}: {path[0]} is a group; set one of its fields")
        value = _parse_value(text, current, key)
    else:
        if not dataclasses.is_dataclass(current):
            raise ValueError(f"--set {key}: {path[0]} has no sub-fields")
        value = _replace_path(current, path[1:], text, key)
    return dataclasses.replace(obj, **{path[0]: value})
