"""The metric log of a run: scalars as JSON lines (`<run>/metrics.jsonl`) and TensorBoard
(`<run>/tb/`), written by process 0 only.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax

from nmjax import atomic
from nmjax.run_folder import METRICS_FILE, TENSORBOARD_DIR


class MetricWriter:
    """Scalars to `<run>/metrics.jsonl` (one JSON object per line) and TensorBoard `<run>/tb/`.

    With `resume_step`, records after that step (written by the interrupted part of a run) are
    dropped, so that the log of a resumed run reads like one of an uninterrupted run.
    The JSONL file is rewritten atomically on every call (it stays small: one line per log step).
    """

    def __init__(self, run_dir: str | Path, resume_step: int | None = None):
        from tensorboardX import SummaryWriter  # heavy import, only where logging happens

        self.path = Path(run_dir) / METRICS_FILE
        self._lines: list[str] = []
        if self.path.is_file():
            for line in self.path.read_text().splitlines():
                try:
                    record = json.loads(line)
                except json.JSONDecodeError:
                    continue  # a line torn by a crash of an older writer
                if resume_step is None or record.get("step", 0) <= resume_step:
                    self._lines.append(line)
        purge = None if resume_step is None else resume_step + 1
        self._tb = SummaryWriter(str(Path(run_dir) / TENSORBOARD_DIR), purge_step=purge)

    def write_scalars(self, step: int, scalars: Mapping[str, Any]) -> None:
        """Logs `scalars` (name -> number or 0-d array) at `step`."""
        values = {k: float(v) for k, v in scalars.items()}
        self._lines.append(json.dumps({"step": int(step), **values}))
        atomic.write_text(self.path, "\n".join(self._lines) + "\n")
        for name, value in values.items():
            self._tb.add_scalar(name, value, int(step))
        self._tb.flush()

    def close(self) -> None:
        self._tb.close()


class NullWriter:
    """The metric writer of the non-primary hosts: writes nothing."""

    def write_scalars(self, step: int, scalars: Mapping[str, Any]) -> None:
        del step, scalars

    def close(self) -> None:
        pass


def metric_writer(run_dir: str | Path, resume_step: int | None = None) -> Any:
    """`MetricWriter` on process 0 (the one that writes logs), a `NullWriter` on the others."""
    if jax.process_index() == 0:
        return MetricWriter(run_dir, resume_step=resume_step)
    return NullWriter()


def read_metrics(run_dir: str | Path) -> list[dict[str, float]]:
    """Parses `<run_dir>/metrics.jsonl` into a list of records."""
    path = Path(run_dir) / METRICS_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found; has the run logged anything yet?")
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
