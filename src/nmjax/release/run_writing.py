"""What `import_release` writes into each run folder: config.json and checkpoint 0 (`save_run`),
and the phase-1 artefacts of the imported detector (`write_phase1_artifacts`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


def write_phase1_artifacts(run: Path, detector: Any, keypoints: np.ndarray, voxels: Any) -> None:
    """affinity.npy and keypoint_stats.npz as `train.skel.write_artifacts` writes them."""
    from nmjax import atomic, runs

    flat = np.asarray(keypoints, np.float32).reshape(-1, *keypoints.shape[-2:])  # (frames, K, 4)
    atomic.save_npy(run / runs.AFFINITY_FILE, np.asarray(detector.affinity(), np.float32))
    atomic.save_npz(
        run / runs.STATS_FILE,
        intensities=flat[:, :, 3].mean(axis=0),
        rest_positions=flat[:, :, :3].mean(axis=0),
        example_voxels=np.asarray(voxels, np.float32),
        example_keypoints=flat[0],
    )


def save_run(folder: Path, cfg: Any, model: Any, optimizer: Any) -> None:
    """config.json and the model with a fresh optimizer state as checkpoint 0 (the imported
    parameters before any nmjax step), in the layout the trainers restore."""
    from nmjax.train import common

    common.prepare_run_dir(folder, resume=False, config=cfg)
    _, state = common.init_state(model, optimizer)
    with common.Checkpointer(folder / common.CHECKPOINTS, cfg.keep_checkpoints) as ckpt:
        ckpt.save(0, state)
