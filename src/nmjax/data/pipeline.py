"""Phase-1 input pipeline with grain: random crops -> per-crop normalisation -> voxels -> batches.

One element is one crop (paper Sec. B.1): a sequence drawn from a per-epoch shuffle of the split,
a random start, `cfg.frames` frames every `cfg.sample_rate` original frames (padded with the last
frame), normalised with one bounding box over the crop (docs/architecture.md §4) and voxelised at
`cfg.grid`. The grain graph is

    MapDataset.range(num_sequences).seed(seed).shuffle().repeat()   # infinite, reshuffled per epoch
      .random_map(crop)                                             # rng from (seed, index)
      .to_iter_dataset(threads, prefetch buffer) [.mp_prefetch(workers)]
      .batch(B, drop_remainder=True)

so every batch depends only on the seed and its position in the stream, not on threads or timing,
and the iterator's state (`get_state` / `set_state`, or `grain.checkpoint.CheckpointSave`) is the
position: a restored iterator yields exactly the batches the original would have.

With several hosts, host p of P takes every P-th crop of that one stream (`[p::P]` after the
random map, so each crop keeps its global index and random start) in batches of B / P: at every
step the hosts' batches together are exactly the crops of the single-host batch.
"""

from __future__ import annotations

import dataclasses

import grain
import jax
import numpy as np
from absl import flags

from nmjax.config import DataConfig, check_batch_split
from nmjax.data.datasets import (
    Sequence,
    crop_indices,
    crop_sequence,
    load_sequences,
    sample_start,
)
from nmjax.data.normalize import normalize_sequence
from nmjax.data.voxelize import voxelize

__all__ = [
    "Augmentation",
    "CropVoxelizer",
    "augment_crop",
    "crop_sequence",
    "eval_batches",
    "skel_iterator",
]


@dataclasses.dataclass(frozen=True)
class Augmentation:
    """Random rotation about the up axis (+-`rotate_degrees`) and shrink (by up to
    `scale_jitter`) of a training crop; see `DataConfig.rotate_degrees`."""

    rotate_degrees: float = 0.0
    scale_jitter: float = 0.0
    up_axis: int = 2

    def __post_init__(self):
        if not 0.0 <= self.rotate_degrees <= 180.0:
            raise ValueError(f"data.rotate_degrees must be in [0, 180], got {self.rotate_degrees}")
        if not 0.0 <= self.scale_jitter < 1.0:
            raise ValueError(f"data.scale_jitter must be in [0, 1), got {self.scale_jitter}")
        if self.up_axis not in (0, 1, 2):
            raise ValueError(f"data.up_axis must be 0, 1 or 2 (x, y, z), got {self.up_axis}")

    @classmethod
    def from_config(cls, cfg: DataConfig) -> Augmentation | None:
        """The augmentation of `cfg`'s training crops, None when it is off."""
        aug = cls(cfg.rotate_degrees, cfg.scale_jitter, cfg.up_axis)
        return aug if aug.rotate_degrees > 0 or aug.scale_jitter > 0 else None


def augment_crop(
    points: np.ndarray, joints: np.ndarray | None, rng: np.random.Generator, aug: Augmentation
) -> tuple[np.ndarray, np.ndarray | None]:
    """One random draw of `aug` applied to a crop, normalised to [-1, 1)^3 as `normalize_sequence`
    does; the same rotation and scale for every frame, so the motion itself is unchanged.

    Args:
      points: (T, N, 3) raw points of the crop.
      joints: optional (T, J, 3) ground-truth joints; they follow the points.
      rng: the crop's generator; two draws (angle, scale).
      aug: the ranges.

    Returns:
      (points', joints') float32, inside [-1, 1)^3: rotated about `aug.up_axis` through the
      crop's mean point, normalised, then p' = -1 + s (p' + 1) with s ~ U[1 - scale_jitter, 1].
    """
    angle = np.deg2rad(rng.uniform(-aug.rotate_degrees, aug.rotate_degrees))
    scale = rng.uniform(1.0 - aug.scale_jitter, 1.0)
    a, b = [axis for axis in range(3) if axis != aug.up_axis]
    rot = np.eye(3)
    rot[a, a] = rot[b, b] = np.cos(angle)
    rot[a, b], rot[b, a] = -np.sin(angle), np.sin(angle)
    centre = np.asarray(points, dtype=np.float64).reshape(-1, 3).mean(axis=0)

    def turn(x):
        return None if x is None else (np.asarray(x, dtype=np.float64) - centre) @ rot.T + centre

    points, joints = normalize_sequence(turn(points), turn(joints))
    points = (scale * (points + 1.0) - 1.0).astype(np.float32)
    if joints is not None:
        joints = (scale * (joints + 1.0) - 1.0).astype(np.float32)
    return points, joints


class CropVoxelizer:
    """grain random map: sequence index -> {"voxels": (T,G,G,G), "joints": (T,J,3)} of one crop.

    Pickles as file paths only (worker processes reopen the files memory-mapped), so a large
    dataset is never copied into the workers.
    """

    def __init__(
        self,
        sequences: list[Sequence],
        frames: int,
        sample_rate: int,
        grid: int,
        augmentation: Augmentation | None = None,
    ):
        if frames < 1 or sample_rate < 1 or grid < 1:
            raise ValueError(
                f"DataConfig.frames, .sample_rate and .grid must be >= 1, got {frames}, "
                f"{sample_rate}, {grid}"
            )
        self.frames, self.sample_rate, self.grid = frames, sample_rate, grid
        self.augmentation = augmentation
        joint_counts = {None if s.joints is None else s.joints.shape[1] for s in sequences}
        # Joints are batched only when every sequence has the same number of them.
        self.with_joints = None not in joint_counts and len(joint_counts) == 1
        self.paths = [(s.path, s.joints_path) for s in sequences]
        self.num_frames = [s.num_frames for s in sequences]
        self._arrays: list[tuple[np.ndarray, np.ndarray | None]] | None = [
            (s.vertices, s.joints) for s in sequences
        ]

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_arrays": None}

    def _sequence(self, index: int) -> tuple[np.ndarray, np.ndarray | None]:
        if self._arrays is None:  # in a worker process: reopen (validated by the loader)
            self._arrays = [
                (np.load(v, mmap_mode="r"), None if j is None else np.load(j, mmap_mode="r"))
                for v, j in self.paths
            ]
        return self._arrays[index]

    def crop(
        self, index: int, start: int, rng: np.random.Generator | None = None
    ) -> dict[str, np.ndarray]:
        """The crop of sequence `index` starting at frame `start`, normalised and voxelised;
        augmented with draws from `rng` when this voxelizer has an augmentation."""
        vertices, joints = self._sequence(index)
        idx = crop_indices(self.num_frames[index], self.frames, self.sample_rate, start)
        points = np.asarray(vertices[idx], dtype=np.float32)
        crop_joints = np.asarray(joints[idx], dtype=np.float32) if self.with_joints else None
        if self.augmentation is not None and rng is not None:
            points, crop_joints = augment_crop(points, crop_joints, rng, self.augmentation)
        else:
            points, crop_joints = normalize_sequence(points, crop_joints)
        element = {"voxels": voxelize(points, self.grid)}
        if crop_joints is not None:
            element["joints"] = crop_joints
        return element

    def __call__(self, index: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
        index = int(index)
        start = sample_start(rng, self.num_frames[index], self.frames, self.sample_rate)
        return self.crop(index, start, rng)


def _dataset(
    sequences: list[Sequence],
    cfg: DataConfig,
    seed: int,
    shard: tuple[int, int] = (0, 1),
    augment: bool = False,
) -> grain.IterDataset:
    augmentation = Augmentation.from_config(cfg) if augment else None
    crop = CropVoxelizer(sequences, cfg.frames, cfg.sample_rate, cfg.grid, augmentation)
    ds = grain.MapDataset.range(len(sequences)).seed(seed).shuffle().repeat()
    ds = ds.random_map(crop)
    index, count = shard
    batch_size = cfg.batch_size
    if count > 1:
        over = f"the hosts ({count}), each loading data.batch_size / {count} crops per step"
        check_batch_split(cfg.batch_size, count, "data.batch_size", over)
        batch_size = cfg.batch_size // count
        ds = ds[index::count]
    buffer = max(cfg.prefetch, 1) * batch_size
    threads = 1 if cfg.prefetch > 0 else 0
    it_ds = ds.to_iter_dataset(grain.ReadOptions(num_threads=threads, prefetch_buffer_size=buffer))
    if cfg.worker_count > 0:
        # grain's worker processes read absl flags; outside an absl app nobody parses them.
        if not flags.FLAGS.is_parsed():
            flags.FLAGS.mark_as_parsed()
        it_ds = it_ds.mp_prefetch(grain.MultiprocessingOptions(num_workers=cfg.worker_count))
    return it_ds.batch(batch_size, drop_remainder=True)


def skel_iterator(
    cfg: DataConfig,
    split: str = "train",
    seed: int | None = None,
    *,
    process_index: int | None = None,
    process_count: int | None = None,
) -> grain.DatasetIterator:
    """The grain iterator of phase-1 batches; checkpoint it with `get_state` / `set_state`.

    Args:
      cfg: dataset name and root, grid G, frames T, sample rate, global batch size B, workers,
        prefetch.
      split: "train" or "test".
      seed: stream seed; default `cfg.seed`.
      process_index, process_count: this host's shard of the stream; default
        `jax.process_index()` / `jax.process_count()` (0 / 1 on a single host).

    Returns:
      an infinite `grain.DatasetIterator` of dicts {"voxels": (B/P,T,G,G,G) float32, "joints":
      (B/P,T,J,3) float32 (only when every sequence has ground-truth joints)}, P = process count.
    """
    if cfg.batch_size < 1:
        raise ValueError(f"DataConfig.batch_size must be >= 1, got {cfg.batch_size}")
    if process_index is None or process_count is None:
        process_index, process_count = jax.process_index(), jax.process_count()
    if not 0 <= process_index < process_count:
        raise ValueError(f"process_index {process_index} is not in 0..{process_count - 1}")
    sequences = load_sequences(cfg.name, split, cfg.root)
    ds = _dataset(
        sequences,
        cfg,
        cfg.seed if seed is None else seed,
        (process_index, process_count),
        augment=split == "train",
    )
    return iter(ds)


def eval_batches(
    cfg: DataConfig, split: str = "test", num_batches: int = 4, seed: int = 0
) -> list[dict[str, np.ndarray]]:
    """The first `num_batches` batches of the `split` stream for `seed`: a fixed evaluation set.

    Computed in the main process (no workers), so the list is the same on every call.
    """
    if num_batches < 1:
        raise ValueError(f"num_batches must be >= 1, got {num_batches}")
    sequences = load_sequences(cfg.name, split, cfg.root)
    ds = _dataset(sequences, dataclasses.replace(cfg, worker_count=0), seed)
    iterator = iter(ds)
    return [next(iterator) for _ in range(num_batches)]
