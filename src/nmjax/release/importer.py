"""`import_release`: the checkpoint and options as two run folders, written atomically (a
temporary folder renamed onto the target at the end)."""

from __future__ import annotations

import datetime
import json
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from nmjax.release.checkpoint import Checkpoint, read_checkpoint, read_options
from nmjax.release.convert import build_networks
from nmjax.release.layout import network_widths
from nmjax.release.options import configs_from_options
from nmjax.release.run_writing import save_run

PROVENANCE_FILE = "release.json"
DEMO_SOURCE = "data/demo/source/gHO_sBM_cAll_d20_mHO1_ch05.npy"  # in the authors' repository


def import_record(checkpoint: Path, ckpt: Checkpoint, options_path: Path, options: Mapping) -> dict:
    """What release.json records beside the provenance stamp (`nmjax.provenance`: the nmjax
    commit and working tree, date, command, machine, versions): the checkpoint (path, bytes,
    sha256, tensors, values) and the options as read."""
    return {
        "checkpoint": str(checkpoint.resolve()),
        "sha256": ckpt.sha256,
        "bytes": ckpt.size,
        "tensors": len(ckpt.tensors),
        "values": int(sum(a.size for a in ckpt.tensors.values())),
        "options_file": str(options_path.resolve()),
        "options": json.loads(json.dumps(dict(options), default=repr)),
    }


def keypoint_motion(detector: Any, cfg: Any, example: str | Path | None) -> tuple:
    """Keypoints (..., T, K, 4) and one voxel frame (G, G, G) of the motion whose statistics go
    into keypoint_stats.npz (the intensities skeleton.json prunes by, the figure's example).

    With `example`, a point-sequence .npy (T, N, >= 3): its first phase-1 crop (T frames every
    `data.sample_rate`-th, one bounding box, `tasks.point_file_keypoints`). Without, the
    evaluation batches of the dataset's test split, the frames `train-skel` measures them on.

    Raises:
      ValueError, FileNotFoundError: an unreadable example or dataset (`check_dataset` first).
    """
    from nmjax.train import trained

    data = cfg.data
    det = trained.Detector.of(detector, cfg, "")
    if example is not None:
        from nmjax.tasks import point_file_keypoints

        keypoints, voxels = point_file_keypoints(det, example, data.frames, data.sample_rate)
        return keypoints, voxels[0]
    from nmjax.data import pipeline

    batches = pipeline.eval_batches(data, "test", cfg.val_batches, seed=cfg.seed)
    keypoints = np.stack([det.keypoints(b["voxels"]) for b in batches])
    return keypoints, np.asarray(batches[0]["voxels"][0, 0], np.float32)


def check_dataset(data: Any) -> None:
    """Refuses (FileNotFoundError naming both fixes) a dataset whose test split cannot be read,
    when it is to give the keypoint statistics."""
    from nmjax.data.datasets import load_sequences

    try:
        load_sequences(data.name, "test", data.root)
    except (FileNotFoundError, ValueError) as err:
        raise FileNotFoundError(
            f"skeleton.json's keypoint intensities need a motion: give --example POINTS.npy "
            f"(e.g. the authors' {DEMO_SOURCE}) or prepare the {data.name!r} dataset "
            f"({' '.join(str(err).split())})"
        ) from err


def check_run_folder(run: str | Path, overwrite: bool) -> Path:
    """`run` as a Path, after refusing (ValueError) a file, or a folder that holds anything
    unless `overwrite`; `overwrite` replaces only an earlier import (a folder whose skel/ and
    dyn/ hold release.json), never another folder.
    """
    run = Path(run)
    if not run.exists() or (run.is_dir() and not any(run.iterdir())):
        return run
    if not run.is_dir():
        raise ValueError(f"--run {run} is a file; give a folder path")
    if not overwrite:
        raise ValueError(
            f"--run {run} already exists; pass --overwrite to replace it, or choose another folder"
        )
    earlier = all((run / sub / PROVENANCE_FILE).is_file() for sub in ("skel", "dyn"))
    if not earlier or run.resolve() == Path.cwd().resolve():
        raise ValueError(
            f"--run {run} is not a folder `nmjax import-release` wrote, so --overwrite does not "
            "replace it; choose another folder"
        )
    return run


def import_release(
    checkpoint: str | Path,
    options: str | Path,
    run: str | Path,
    *,
    overwrite: bool = False,
    example: str | Path | None = None,
    progress: bool = True,
) -> tuple[Path, Path]:
    """The released model as the run folders `run`/skel (phase 1) and `run`/dyn (phase 2).

    Reads the checkpoint and options (`read_checkpoint`, `read_options`), builds both networks
    from the configurations of the options and fills every parameter (`build_networks`), then
    writes, into a temporary folder beside `run` that is renamed onto it at the end:
    skel/: config.json, checkpoints/0, affinity.npy, keypoint_stats.npz (of `keypoint_motion`),
    skeleton.json and its figure (`trained.extract_run_skeleton`: Algorithm 1 on the imported
    affinity); dyn/: config.json naming skel as its phase-1 run, checkpoints/0; and in both
    release.json (`import_record` and the `nmjax.provenance` stamp). Nothing is left behind when
    a step fails.

    Returns:
      (skel folder, dyn folder).

    Raises:
      FileNotFoundError, ValueError: a missing, truncated, legacy or refused file, options that
        do not match the tensors, an existing `run` without `overwrite`, no motion for the
        keypoint statistics.
    """
    from tqdm import tqdm

    from nmjax import provenance, run_folder
    from nmjax.data.meshes import load_point_sequence
    from nmjax.train import dyn, skel, trained

    run = check_run_folder(run, overwrite)
    checkpoint, options = Path(checkpoint), Path(options)
    if example is not None:
        if not Path(example).is_file():
            raise FileNotFoundError(f"--example {example} not found; give a point-sequence .npy")
        load_point_sequence(example)  # refuses another shape before anything is computed
    # Every check that can refuse the inputs comes before the progress bar and the first write.
    opts = read_options(options)
    ckpt = read_checkpoint(checkpoint)
    skel_cfg, dyn_cfg = configs_from_options(opts, network_widths(ckpt.tensors), run)
    if example is None:
        check_dataset(skel_cfg.data)
    detector, dynamics, _ = build_networks(ckpt.tensors, skel_cfg, dyn_cfg)
    stamp = provenance.stamp()  # taken when the work starts, as every results writer does
    record = import_record(checkpoint, ckpt, options, opts)
    record["keypoint_statistics"] = str(example) if example else f"{dyn_cfg.data.name} test split"
    with tqdm(total=2, desc="import-release", leave=False, disable=not progress) as bar:
        bar.set_postfix_str("keypoint statistics")
        keypoints, voxels = keypoint_motion(detector, skel_cfg, example)
        bar.update()
        bar.set_postfix_str("write")
        target = run.resolve()
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = (
            target.parent / f".{target.name}.import-{datetime.datetime.now().strftime('%H%M%S%f')}"
        )
        try:
            save_run(tmp / "skel", skel_cfg, detector, skel.StepSettings.of(skel_cfg).optimizer)
            run_folder.write_phase1_artifacts(tmp / "skel", detector.affinity(), keypoints, voxels)
            trained.extract_run_skeleton(tmp / "skel")
            save_run(tmp / "dyn", dyn_cfg, dynamics, dyn.StepSettings.of(dyn_cfg).optimizer)
            for folder in ("skel", "dyn"):
                provenance.write_json(tmp / folder / PROVENANCE_FILE, record, stamp)
            if target.exists():
                shutil.rmtree(target)
            tmp.rename(target)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        bar.update()
    return run / "skel", run / "dyn"
