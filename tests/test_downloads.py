"""`nmjax prepare-data` on the real sets as downloaded: DeformingThings4D `.anime`, D-FAUST
`registrations_{m,f}.hdf5`, the published splits, skip-on-rerun, and the one-line refusals.

Every file is tiny and written here: a two-triangle mesh (not flat) moving over a few frames, so
that each prepared point can be checked against the moved triangles it was sampled from.
"""

from __future__ import annotations

import json
import re

import h5py
import numpy as np
import pytest

from nmjax.cli import main as nmjax_main
from nmjax.data import dt4d, splits, streaming
from nmjax.data.datasets import load_sequences
from nmjax.data.layout import split_by_frames

POINTS = 64
FACES = np.array([[0, 1, 2], [1, 3, 2]])


def prepare_main(argv: list[str]) -> int:
    return nmjax_main(["prepare-data", *argv])


def moved(t: int, shift: float = 0.0) -> np.ndarray:
    """(4, 3) vertices of frame t: a folded quad moved by t along x, its far corner lifted by
    0.3 t (a non-rigid motion); `shift` sets sequences apart."""
    base = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.5]], dtype=np.float32)
    base[:, 0] += t + shift
    base[3, 2] += 0.3 * t
    return base


def frames_of(count: int, shift: float = 0.0) -> np.ndarray:
    return np.stack([moved(t, shift) for t in range(count)])


def distance_to_triangles(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(N,) distance of each point to the nearest of `triangles` (F, 3, 3) that it projects
    into (inf when it projects into none)."""
    best = np.full(len(points), np.inf)
    for a, b, c in triangles.astype(np.float64):
        normal = np.cross(b - a, c - a)
        basis = np.stack([b - a, c - a, normal / np.linalg.norm(normal)], axis=1)
        u, v, w = np.linalg.solve(basis, (points - a).T)
        inside = (u >= -1e-5) & (v >= -1e-5) & (u + v <= 1 + 1e-5)
        best = np.where(inside, np.minimum(best, np.abs(w)), best)
    return best


def assert_on_frames(vertices: np.ndarray, shift: float = 0.0) -> None:
    """Frame t of `vertices` (T, N, 3) lies on frame t's moved triangles."""
    assert vertices.shape[1:] == (POINTS, 3) and vertices.dtype == np.float32
    for t, frame in enumerate(vertices):
        assert distance_to_triangles(frame, moved(t, shift)[FACES]).max() < 1e-5


def write_anime(path, vertices: np.ndarray, faces: np.ndarray = FACES) -> None:
    """A DeformingThings4D `.anime` file: counts, frame 0, faces, offsets from frame 0."""
    path.parent.mkdir(parents=True, exist_ok=True)
    counts = np.array([len(vertices), vertices.shape[1], len(faces)], dtype="<i4")
    offsets = vertices[1:] - vertices[0]
    parts = (counts, vertices[0].astype("<f4"), faces.astype("<i4"), offsets.astype("<f4"))
    path.write_bytes(b"".join(part.tobytes() for part in parts))


def write_registrations(path, sequences: dict[str, np.ndarray], faces=FACES) -> None:
    """A D-FAUST registrations file: one (V, 3, T) dataset per sequence, and `faces`."""
    with h5py.File(path, "w") as f:
        for key, vertices in sequences.items():
            f.create_dataset(key, data=np.transpose(vertices, (1, 2, 0)))
        if faces is not None:
            f.create_dataset("faces", data=faces)


ANIMALS = {"bear3EP_Walk": 3, "cattleAB_Run": 4, "catG9_Jump": 3, "alien_Wave": 3}


def write_animals(source) -> None:
    for i, (seq, count) in enumerate(ANIMALS.items()):
        write_anime(source / seq / f"{seq}.anime", frames_of(count, shift=10.0 * i))


def test_published_lists_ship_with_the_package():
    sizes = {n: tuple(map(len, splits.read_published(n).values())) for n in splits.PUBLISHED_SPLITS}
    assert sizes == {"aist": (2461, 272), "dfaust": (9, 1), "animals": (28, 10)}
    split, left_out = splits.published_split("dfaust", ["50025_hips", "50002_knees", "9_x"])
    assert split == {"train": ["50002_knees"], "test": ["50025_hips"]} and left_out == ["9_x"]
    with pytest.raises(ValueError, match="no published split"):
        splits.read_published("hanco")


def test_anime_animals_published_split(tmp_path, capsys):
    source, root = tmp_path / "animals", tmp_path / "out"
    write_animals(source)
    argv = ["--data", "animals", "--from", str(source), "--root", str(root)]
    assert prepare_main([*argv, "--points", str(POINTS)]) == 0
    out = capsys.readouterr().out
    # The species list: bear is a test species; cattle (not cat) and cat are train species.
    split = {"train": ["catG9_Jump", "cattleAB_Run"], "test": ["bear3EP_Walk"]}
    assert json.loads((root / "split.json").read_text()) == split
    meta = json.loads((root / "meta.json").read_text())
    assert meta["left_out"] == ["alien_Wave"] and meta["format"] == "dt4d-anime"
    assert meta["frames"] == {seq: ANIMALS[seq] for seq in sum(split.values(), [])}
    assert "3 sequences (3 written, 0 already there), 10 frames, 640 points" in out
    assert "1 in neither published list, left out: alien_Wave" in out
    assert not (root / "preparing.json").exists()
    shifts = {seq: 10.0 * i for i, seq in enumerate(ANIMALS)}
    for name in ("train", "test"):
        loaded = load_sequences("animals", name, root)
        assert [s.name for s in loaded] == split[name]
        for seq in loaded:
            assert seq.joints is None and seq.num_frames == ANIMALS[seq.name]
            assert_on_frames(np.asarray(seq.vertices), shifts[seq.name])
    # The humanoids have no published list: 9:1 by frames over every sequence.
    humans = tmp_path / "humans"
    code = prepare_main(["--data", "dt4d-humanoids", "--from", str(source), "--root", str(humans)])
    assert code == 0
    assert json.loads((humans / "split.json").read_text()) == split_by_frames(ANIMALS)


def test_anime_reader_reads_only_the_frames_asked_for(tmp_path):
    path = tmp_path / "a" / "a.anime"
    write_anime(path, frames_of(5))
    header = dt4d.read_anime_header(path)
    assert (header.frames, header.vertices, header.triangles) == (5, 4, 2)
    vertices, faces = dt4d.read_anime(header, 2)
    np.testing.assert_allclose(vertices, frames_of(2), atol=1e-6)
    np.testing.assert_array_equal(faces, FACES)


def test_dfaust_registrations(tmp_path, capsys):
    source, root = tmp_path / "dfaust", tmp_path / "out"
    source.mkdir()
    write_registrations(
        source / "registrations_m.hdf5",
        {"50002_hips": frames_of(3), "50025_hips": frames_of(4, shift=5.0)},
    )
    base = ["--data", "dfaust", "--from", str(source), "--points", str(POINTS)]
    assert prepare_main([*base, "--root", str(root)]) == 0
    assert "2 sequences (2 written" in capsys.readouterr().out
    split = {"train": ["50002_hips"], "test": ["50025_hips"]}
    assert json.loads((root / "split.json").read_text()) == split
    (train,) = load_sequences("dfaust", "train", root)
    (test,) = load_sequences("dfaust", "test", root)
    assert train.num_frames == 3 and test.num_frames == 4
    assert_on_frames(np.asarray(train.vertices))
    assert_on_frames(np.asarray(test.vertices), shift=5.0)
    # A part gives the bytes of the whole: seeds follow the sequence's name and frame only.
    part = tmp_path / "part"
    assert prepare_main([*base, "--root", str(part), "--subjects", "50025", "--frames", "2"]) == 0
    assert json.loads((part / "split.json").read_text()) == {"train": [], "test": ["50025_hips"]}
    np.testing.assert_array_equal(np.load(part / "test/vertices/50025_hips.npy"), test.vertices[:2])
    motion = tmp_path / "motion"
    assert prepare_main([*base, "--root", str(motion), "--sequences", "hips"]) == 0
    assert sorted(json.loads((motion / "meta.json").read_text())["frames"]) == sorted(
        split["train"] + split["test"]
    )


def test_rerun_skips_what_is_written(tmp_path, capsys, monkeypatch):
    source, root = tmp_path / "animals", tmp_path / "out"
    write_animals(source)
    argv = ["--data", "animals", "--from", str(source), "--root", str(root)]
    argv += ["--points", str(POINTS)]
    # Interrupted while sampling the second sequence (train: catG9_Jump, then cattleAB_Run).
    calls = []
    real_sample = dt4d.sample_mesh_sequence

    def interrupted(*args):
        calls.append(args[-1])
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real_sample(*args)

    monkeypatch.setattr(dt4d, "sample_mesh_sequence", interrupted)
    with pytest.raises(KeyboardInterrupt):
        prepare_main(argv)
    monkeypatch.setattr(dt4d, "sample_mesh_sequence", real_sample)
    first = root / "train" / "vertices" / "catG9_Jump.npy"
    assert first.is_file() and (root / "preparing.json").is_file()
    assert not (root / "meta.json").exists()
    assert not list(root.rglob("*.tmp"))
    with pytest.raises(FileNotFoundError, match="unfinished preparation"):
        load_sequences("animals", "train", root)
    # Other settings cannot continue it.
    capsys.readouterr()
    assert prepare_main([*argv[:-1], "32"]) == 2
    assert "other settings" in capsys.readouterr().err
    stamp = first.stat().st_mtime_ns
    assert prepare_main(argv) == 0
    assert "3 sequences (2 written, 1 already there)" in capsys.readouterr().out
    assert first.stat().st_mtime_ns == stamp and not (root / "preparing.json").exists()
    # Continued = prepared in one go.
    fresh = tmp_path / "fresh"
    assert prepare_main([*argv[:4], "--root", str(fresh), "--points", str(POINTS)]) == 0
    for path in sorted(fresh.rglob("*.npy")):
        assert (root / path.relative_to(fresh)).read_bytes() == path.read_bytes()
    # Finished: left alone; --overwrite writes everything again.
    assert prepare_main(argv) == 0
    assert "--overwrite" in capsys.readouterr().out
    assert prepare_main([*argv, "--overwrite"]) == 0
    assert "3 sequences (3 written, 0 already there)" in capsys.readouterr().out
    assert first.stat().st_mtime_ns != stamp


def test_rerun_moves_a_sequence_whose_split_changed(tmp_path, capsys):
    source, root = tmp_path / "raw", tmp_path / "out"
    write_animals(source)
    names = sorted(ANIMALS)
    (source / "split.json").write_text(json.dumps({"train": names[:3], "test": names[3:]}))
    argv = [
        "--data",
        "dt4d-humanoids",
        "--from",
        str(source),
        "--root",
        str(root),
        "--points",
        "16",
    ]
    assert prepare_main(argv) == 0
    stamps = {p.name: p.stat().st_mtime_ns for p in root.rglob("*.npy")}
    (root / "meta.json").unlink()  # as if interrupted before the index was written
    settings = {"name": "dt4d-humanoids", "points": 16, "seed": 0, "source": str(source)}
    (root / "preparing.json").write_text(json.dumps(settings))
    split = {"train": names[1:], "test": names[:1]}
    (source / "split.json").write_text(json.dumps(split))
    capsys.readouterr()
    assert prepare_main(argv) == 0
    assert "4 sequences (0 written, 4 already there)" in capsys.readouterr().out
    assert json.loads((root / "split.json").read_text()) == split
    for name in ("train", "test"):
        assert sorted(p.stem for p in (root / name / "vertices").glob("*.npy")) == split[name]
    assert {p.name: p.stat().st_mtime_ns for p in root.rglob("*.npy")} == stamps


def _bad_anime(source, case):
    write_animals(source)
    path = source / "bear3EP_Walk" / "bear3EP_Walk.anime"
    if case == "truncated":
        path.write_bytes(path.read_bytes()[:-4])
    elif case == "too-long":
        path.write_bytes(path.read_bytes() + b"\0" * 4)
    elif case == "header":
        path.write_bytes(b"\1\0")
    return path


def _bad_registrations(source, case):
    source.mkdir()
    path = source / "registrations_f.hdf5"
    good = {"50002_hips": frames_of(3)}
    if case == "no-faces":
        write_registrations(path, good, faces=None)
    elif case == "wrong-shape":
        with h5py.File(path, "w") as f:
            f.create_dataset("faces", data=FACES)
            f.create_dataset("50002_hips", data=np.zeros((4, 5, 3), np.float32))
    elif case == "not-hdf5":
        path.write_bytes(b"not an hdf5 file")
    else:
        write_registrations(path, good)
    return path


@pytest.mark.parametrize(
    "case, extra, match",
    [
        ("truncated", [], r"bear3EP_Walk\.anime: truncated: nf=3, nv=4, nt=2 make \d+ bytes"),
        ("too-long", [], r"bear3EP_Walk\.anime: longer than its header says"),
        ("header", [], r"bear3EP_Walk\.anime: 2 bytes, too short for an \.anime header"),
        ("no-faces", [], r"registrations_f\.hdf5: no 'faces' dataset"),
        ("wrong-shape", [], r"registrations_f\.hdf5: '50002_hips' has shape \(4, 5, 3\)"),
        ("not-hdf5", [], r"registrations_f\.hdf5: not a readable HDF5 file"),
        ("empty", [], r"no sub-folder holds .* or registrations_m\.hdf5"),
        ("empty-animals", [], r"no sub-folder holds .* or <seq>/<seq>\.anime"),
        ("subjects", ["--subjects", "50099"], r"--subjects 50099: not in .*registrations_f"),
        ("sequences", ["--sequences", "jumps"], r"--sequences: jumps not in"),
        ("not-animals", [], r"none of its 1 sequences \(human_Run, \.\.\.\) is in the published"),
        ("subjects-animals", ["--subjects", "1"], r"--subjects picks D-FAUST subjects"),
    ],
)
def test_bad_download_is_one_line(tmp_path, capsys, case, extra, match):
    source, root = tmp_path / "raw", tmp_path / "out"
    name = "dfaust"
    if case in ("truncated", "too-long", "header", "subjects-animals"):
        name = "animals"
        _bad_anime(source, case)
    elif case in ("empty", "empty-animals"):
        source.mkdir()
        name = "animals" if case == "empty-animals" else "dfaust"
    elif case == "not-animals":
        name = "animals"
        write_anime(source / "human_Run" / "human_Run.anime", frames_of(3))
    else:
        _bad_registrations(source, case)
    argv = ["--data", name, "--from", str(source), "--root", str(root), "--points", "8", *extra]
    assert prepare_main(argv) == 2
    err = capsys.readouterr().err
    assert re.search(match, err), err
    assert len(err.strip().splitlines()) == 1
    assert not root.exists()  # nothing written, not even the folder


def test_bad_input_with_overwrite_keeps_the_prepared_set(tmp_path, capsys):
    source, root = tmp_path / "animals", tmp_path / "out"
    write_animals(source)
    argv = ["--data", "animals", "--from", str(source), "--root", str(root), "--points", "8"]
    assert prepare_main(argv) == 0
    before = sorted(p.relative_to(root) for p in root.rglob("*"))
    _bad_anime(tmp_path / "damaged", "truncated")
    argv[3] = str(tmp_path / "damaged")
    assert prepare_main([*argv, "--overwrite"]) == 2
    assert "truncated" in capsys.readouterr().err
    assert sorted(p.relative_to(root) for p in root.rglob("*")) == before


def test_sample_mesh_sequence_refuses_bad_faces_and_values():
    vertices = frames_of(2)
    seeds = streaming.sequence_seeds(0, "s", 2)
    with pytest.raises(ValueError, match="face indices 0..4 outside the 4 vertices"):
        streaming.sample_mesh_sequence(vertices, np.array([[0, 1, 4]]), 8, seeds, "x.anime")
    vertices[1, 0, 0] = np.nan
    with pytest.raises(ValueError, match="x.anime: vertices contain NaN or inf .*frame 1"):
        streaming.sample_mesh_sequence(vertices, FACES, 8, seeds, "x.anime")
    np.testing.assert_array_equal(seeds, streaming.sequence_seeds(0, "s", 5)[:2])


def test_help_names_the_downloads(capsys):
    assert prepare_main(["--help"]) == 0
    out = capsys.readouterr().out
    for line in (
        "nmjax prepare-data --data dfaust --from DFAUST_ROOT",
        "nmjax prepare-data --data animals --from DT4D_ROOT/animals",
        "nmjax prepare-data --data dt4d-humanoids --from DT4D_ROOT/humanoids",
        "registrations_m.hdf5, registrations_f.hdf5",
        "https://github.com/rabbityl/DeformingThings4D",
        "https://dfaust.is.tue.mpg.de",
    ):
        assert line in out
