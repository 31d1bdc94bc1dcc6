"""DeformingThings4D (Li et al. 2021b) as downloaded: `<root>/<seq>/<seq>.anime`.

The `.anime` format, as the dataset describes it (little-endian):

    int32   nf, nv, nt                  frames, vertices, triangles
    float32 vert_data[nv * 3]           frame 0's vertices, x y z
    int32   face_data[nt * 3]           the triangles, one topology for every frame
    float32 offset_data[(nf-1) * nv * 3]  frame i = vert_data + offset_data[i - 1]

Only the header is read when the sequences are listed (and the file size checked against it);
the frames are read on the sequence's turn. DeformingThings4D has no ground-truth joints.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from nmjax.data.streaming import SourceSequence, sample_mesh_sequence

ANIME_SUFFIX = ".anime"
_INT = np.dtype("<i4")
_FLOAT = np.dtype("<f4")
_HEADER_BYTES = 3 * _INT.itemsize


@dataclasses.dataclass(frozen=True)
class AnimeHeader:
    """The three counts at the start of an `.anime` file."""

    path: Path
    frames: int
    vertices: int
    triangles: int

    @property
    def faces_offset(self) -> int:
        return _HEADER_BYTES + 3 * self.vertices * _FLOAT.itemsize

    @property
    def offsets_offset(self) -> int:
        return self.faces_offset + 3 * self.triangles * _INT.itemsize

    @property
    def size(self) -> int:
        """The file size in bytes that the counts imply."""
        return self.offsets_offset + 3 * (self.frames - 1) * self.vertices * _FLOAT.itemsize


def read_anime_header(path: Path) -> AnimeHeader:
    """Reads and checks the header of the `.anime` file `path`.

    Raises:
      ValueError naming `path`: fewer than 12 bytes, counts below 1, or a file size that does not
      add up to what the counts say (a truncated or damaged download).
    """
    size = path.stat().st_size
    with open(path, "rb") as f:
        counts = np.fromfile(f, dtype=_INT, count=3)
    if counts.size < 3:
        raise ValueError(f"{path}: {size} bytes, too short for an .anime header (nf, nv, nt)")
    header = AnimeHeader(path, *(int(c) for c in counts))
    if min(header.frames, header.vertices, header.triangles) < 1:
        raise ValueError(
            f"{path}: damaged .anime header (nf={header.frames}, nv={header.vertices}, "
            f"nt={header.triangles}); download it again"
        )
    if size != header.size:
        what = "truncated" if size < header.size else "longer than its header says"
        raise ValueError(
            f"{path}: {what}: nf={header.frames}, nv={header.vertices}, nt={header.triangles} "
            f"make {header.size} bytes, the file has {size}; download it again"
        )
    return header


def read_anime(header: AnimeHeader, num_frames: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The first `num_frames` frames (default all) of an `.anime` file.

    Returns:
      (vertices (T, nv, 3) float32: frame 0 plus each frame's offsets, faces (nt, 3) int64).
    """
    frames = header.frames if num_frames is None else min(num_frames, header.frames)
    nv, nt = header.vertices, header.triangles
    with open(header.path, "rb") as f:
        f.seek(_HEADER_BYTES)
        first = np.fromfile(f, dtype=_FLOAT, count=3 * nv).reshape(nv, 3)
        faces = np.fromfile(f, dtype=_INT, count=3 * nt).reshape(nt, 3).astype(np.int64)
        offsets = np.fromfile(f, dtype=_FLOAT, count=3 * nv * (frames - 1))
    vertices = np.empty((frames, nv, 3), dtype=np.float32)
    vertices[0] = first
    vertices[1:] = first + offsets.reshape(frames - 1, nv, 3)
    return vertices, faces


def anime_files(source: Path) -> list[Path]:
    """The `.anime` files of a DeformingThings4D folder: `<source>/<seq>/<seq>.anime`."""
    if not source.is_dir():
        return []
    return sorted(source.glob(f"*/*{ANIME_SUFFIX}"))


def anime_sequences(source: Path) -> list[SourceSequence]:
    """Lists the sequences of a DeformingThings4D folder (`animals/` or `humanoids/`), one per
    `<seq>/<seq>.anime`, reading only the headers.

    Raises:
      ValueError: a damaged header (`read_anime_header`), two files of one name.
    """
    sequences: dict[str, SourceSequence] = {}
    for path in anime_files(source):
        header = read_anime_header(path)
        if path.stem in sequences:
            raise ValueError(f"{path}: a second {path.name} under {source}; keep one")

        def read(points: int, seeds: np.ndarray, header: AnimeHeader = header) -> dict:
            vertices, faces = read_anime(header, len(seeds))
            return {
                "vertices": sample_mesh_sequence(vertices, faces, points, seeds, str(header.path))
            }

        sequences[path.stem] = SourceSequence(path.stem, header.frames, read)
    return list(sequences.values())
