"""Tests of nmjax.rows: the results-row store and the rule that keeps a row."""

from __future__ import annotations

import dataclasses
import json
import subprocess
from pathlib import Path

import pytest

from nmjax import provenance, rows
from nmjax.config import SkelTrainConfig, skel_preset
from nmjax.config_io import config_to_dict, replace_fields

METRICS = {"sc": "the SC-score", "cd": "a Chamfer distance"}
REPO = Path(__file__).parent


def _head() -> str:
    return subprocess.run(
        ["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True, cwd=REPO
    ).stdout.strip()


def _row(cfg, **stamp) -> dict:
    base = {"commit": _head(), "dirty": False, "metrics": METRICS}
    return {
        "body": "synth-arm",
        "step": 1000,
        "config": json.loads(json.dumps(config_to_dict(cfg))),
        "provenance": {**base, **stamp},
    }


def test_a_row_is_kept_only_while_it_is_what_would_be_made(tmp_path):
    store = rows.RowStore(
        tmp_path / "r.json", METRICS, _head(), ("body", "step"), SkelTrainConfig, repo=REPO
    )
    cfg = skel_preset("synth-arm", "tiny")
    row = _row(cfg)
    assert store.keeps(row, cfg)
    assert not store.keeps(None, cfg)
    # Where a run lives and the epoch length the data fills in do not count ...
    moved = replace_fields(
        cfg,
        run="elsewhere",
        data=dataclasses.replace(cfg.data, root="/data/copy"),
        steps_per_epoch=9,
    )
    assert store.keeps(row, moved)
    # ... what it computes does, and so do the metric definitions, a dirty or unrelated commit
    # and the script's own conditions.
    assert not store.keeps(row, replace_fields(cfg, learning_rate=0.5))
    assert not store.keeps(row, replace_fields(cfg, steps=cfg.loop.steps + 1))
    assert not store.keeps(_row(cfg, metrics={"sc": "another SC"}), cfg)
    assert not store.keeps(_row(cfg, dirty=True), cfg)
    assert not store.keeps(_row(cfg, commit="0" * 40), cfg)
    assert not store.keeps(row, cfg, extra=lambda r: r["step"] == 2000)
    later = rows.RowStore(tmp_path / "r.json", METRICS, "0" * 40, ("body", "step"), repo=REPO)
    assert not later.keeps(row, cfg)  # made before the store's `since`: not its descendant


def test_a_config_json_reads_through_its_dataclass(tmp_path):
    # A row stored before a field existed compares as that field's default.
    cfg = skel_preset("synth-arm", "tiny")
    stored = config_to_dict(cfg)
    del stored["loop"]["keep_every"]
    assert rows.comparable(stored, SkelTrainConfig) == rows.comparable(cfg)
    assert rows.comparable(stored) != rows.comparable(cfg)  # as stored, without the class


def test_rows_are_written_stamped_sorted_and_replaced_by_name(tmp_path):
    store = rows.RowStore(tmp_path / "r.json", METRICS, _head(), ("body", "step"))
    stamp = provenance.stamp(METRICS)
    kept = store.put([], {"body": "b", "step": 2, "v": 1})
    kept = store.put(kept, {"body": "a", "step": 5, "v": 2})
    kept = store.put(kept, {"body": "b", "step": 2, "v": 3})  # replaces the first
    store.write(kept, stamp, step_time={"a": 1.0})
    saved = json.loads((tmp_path / "r.json").read_text())
    assert [(r["body"], r["v"]) for r in saved["rows"]] == [("a", 2), ("b", 3)]
    assert saved["metrics"] == METRICS and saved["step_time"] == {"a": 1.0}
    assert saved["provenance"]["metrics"] == METRICS
    assert store.read() == saved["rows"]
    assert store.find(store.read(), body="b", step=2)["v"] == 3
    assert store.find(store.read(), body="b", step=9) is None


def test_a_dirty_checkout_is_refused_unless_allowed(monkeypatch):
    monkeypatch.setattr(provenance, "stamp", lambda *a, **k: {"dirty": True})
    with pytest.raises(SystemExit, match="uncommitted changes"):
        rows.refuse_dirty("script.py", allow_dirty=False)
    rows.refuse_dirty("script.py", allow_dirty=True)
