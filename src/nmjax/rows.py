"""Result rows that fill in across sessions: the one row store of `experiments/`.

An experiment is a list of rows, each made by training and scoring runs that take minutes to
hours; a run folder does not survive a new machine, so each row is written to a committed JSON
file (`RowStore.write`, stamped by `nmjax.provenance`) as soon as it is made, and a later call
keeps the rows that are still what it would compute instead of making them again
(`RowStore.keeps`). A row is kept when

- its configuration is equal to the one the script would train now, read through the
  configuration's dataclass (a field added since reads as its default, as an older run folder's
  config.json does, `run_folder.load_config`), the fields that say where a run lives and not
  what it computes left out (`run_folder.LOCATION_FIELDS`, and `loop.steps_per_epoch`, which
  the data fills in);
- its metric definitions are the script's;
- whatever else the script names is equal (`extra`: evaluation settings, an input row);
- it was made on a clean checkout at a commit that descends from the script's `since`: the
  last commit that changed what such a row computes (move it forward with any such change, and
  the rows made before it are made again).
"""

from __future__ import annotations

import json
import os
import subprocess
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from nmjax import provenance, run_folder
from nmjax.config_io import config_from_dict, config_to_dict, flatten_config


def comparable(config: Mapping[str, Any] | Any, cls: type | None = None) -> dict[str, Any]:
    """A configuration as rows compare it: flat {dotted field: value} as JSON reads it back,
    without `run_folder.LOCATION_FIELDS` and `loop.steps_per_epoch`.

    Args:
      config: a configuration dataclass, or its config.json as a dict.
      cls: the dataclass to read a dict through (its defaults fill fields added since); None:
        compared as stored.
    """
    if not isinstance(config, Mapping):
        config = config_to_dict(config)
    elif cls is not None:
        try:
            config = config_to_dict(config_from_dict(cls, dict(config)))
        except (ValueError, TypeError):  # a field since removed: compared as stored
            pass
    flat = flatten_config(json.loads(json.dumps(config)))
    skip = run_folder.LOCATION_FIELDS | {"loop.steps_per_epoch"}
    return {k: v for k, v in flat.items() if k not in skip}


def descends_from(commit: str | None, ancestor: str, repo: str | os.PathLike = ".") -> bool:
    """Whether `commit` is `ancestor` or one of its descendants in the clone at `repo`."""
    if not commit:
        return False
    done = subprocess.run(
        ["git", "merge-base", "--is-ancestor", ancestor, commit],
        cwd=repo,
        capture_output=True,
    )
    return done.returncode == 0


def refuse_dirty(script: str, allow_dirty: bool) -> None:
    """Stops a row-making script on a checkout with uncommitted changes, whose rows no later
    run could keep, unless `allow_dirty`."""
    if provenance.stamp().get("dirty") is not False and not allow_dirty:
        raise SystemExit(
            f"{script}: the checkout has uncommitted changes (or is not a git clone), so its "
            "rows could not be kept by a later run; commit first, train from a clean worktree, "
            "or pass --allow-dirty"
        )


class RowStore:
    """The rows of one experiment in one JSON file: {"metrics": definitions, "rows": [...]}
    under the provenance stamp of the call that wrote it last.

    Args:
      path: the JSON file.
      metrics: {name: definition} of every measure a row holds (part of the keep rule).
      since: the last commit that changed what a row computes.
      key: the row fields that name a row (e.g. ("body", "seed", "variant")).
      config_class: the configuration dataclass a row's "config" is read through.
      repo: the git clone whose history `since` is looked up in (default: the one holding
        `path`).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        metrics: Mapping[str, str],
        since: str,
        key: tuple[str, ...],
        config_class: type | None = None,
        repo: str | os.PathLike | None = None,
    ):
        self.path = Path(path)
        self.repo = Path(repo) if repo is not None else self.path.parent
        self.metrics = dict(metrics)
        self.since = since
        self.key = key
        self.config_class = config_class

    def read(self) -> list[dict[str, Any]]:
        """The stored rows ([] when the file does not exist yet)."""
        return json.loads(self.path.read_text())["rows"] if self.path.is_file() else []

    def name(self, row: Mapping[str, Any]) -> tuple:
        return tuple(row[k] for k in self.key)

    def find(self, rows: list[dict[str, Any]], **key: Any) -> dict[str, Any] | None:
        """The row of `rows` named by `key` (every field of `self.key`), or None."""
        wanted = tuple(key[k] for k in self.key)
        return next((r for r in rows if self.name(r) == wanted), None)

    def keeps(
        self,
        row: Mapping[str, Any] | None,
        config: Any,
        extra: Callable[[Mapping[str, Any]], bool] | None = None,
    ) -> bool:
        """Whether the stored `row` is what a call would make now with `config` (module doc);
        `extra(row)`: the script's own further conditions."""
        if row is None:
            return False
        stamp = row.get("provenance", {})
        return (
            comparable(row.get("config", {}), self.config_class)
            == comparable(config, self.config_class)
            and stamp.get("metrics") == self.metrics
            and stamp.get("dirty") is False
            and descends_from(stamp.get("commit"), self.since, self.repo)
            and (extra is None or extra(row))
        )

    def put(self, rows: list[dict[str, Any]], row: dict[str, Any]) -> list[dict[str, Any]]:
        """`rows` with `row` in place of the row of the same name (appended if new)."""
        return [r for r in rows if self.name(r) != self.name(row)] + [row]

    def write(
        self,
        rows: list[dict[str, Any]],
        stamp: Mapping[str, Any],
        order: Callable[[Mapping[str, Any]], Any] | None = None,
        **extra: Any,
    ) -> None:
        """Writes `rows` (sorted by `order`, default their names) under `stamp`, atomically,
        with any further top-level fields `extra`."""
        rows = sorted(rows, key=order or self.name)
        body = {"metrics": self.metrics, **extra, "rows": rows}
        provenance.write_json(self.path, body, stamp)
