"""What `import_release` writes into each run folder besides the phase-1 artefacts (those go
through `nmjax.run_folder.write_phase1_artifacts`, as a trained run's do): config.json and
checkpoint 0 (`save_run`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def save_run(folder: Path, cfg: Any, model: Any, optimizer: Any) -> None:
    """config.json and the model with a fresh optimizer state as checkpoint 0 (the imported
    parameters before any nmjax step), in the layout the trainers restore."""
    from nmjax import run_folder
    from nmjax.train import checkpoints, optim

    run_folder.prepare_run_dir(folder, resume=False, config=cfg)
    _, state = optim.init_state(model, optimizer)
    with checkpoints.Checkpointer.of_run(folder, cfg.loop) as ckpt:
        ckpt.save(0, state)
