"""`nmjax import-release`: the reader of PyTorch's zip checkpoint, the name/layout map onto the
nmjax networks (at the release's sizes, from shared/release/), the layout conversions on hand cases,
and the import end to end on a small checkpoint of the same kind. PyTorch is never imported."""

from __future__ import annotations

import io
import json
import pickle
import subprocess
import sys
import zipfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import release_files as rf
from flax import nnx

from nmjax import release
from nmjax.models import blocks, conv_kernels
from nmjax.models.dynamics import GRUCell

FIXTURE = Path(__file__).parent / "release_fixture"
TINY = FIXTURE / "tiny_state_dict.pth"

# --- the reader --------------------------------------------------------------------------------


def test_pytorchs_own_checkpoint_reads_back_to_the_same_arrays():
    ckpt = release.read_checkpoint(TINY)
    with np.load(FIXTURE / "tiny_state_dict.npz") as ref:
        assert list(ckpt.tensors) == list(ref.files)  # the state dict's order
        for name in ref.files:
            got, want = ckpt.tensors[name], ref[name]
            assert type(got) is np.ndarray and got.dtype == want.dtype, name
            assert got.shape == want.shape, name
            np.testing.assert_array_equal(got, want, err_msg=name)
    assert ckpt.size == TINY.stat().st_size and len(ckpt.sha256) == 64
    # Two views of one storage: a transposed one and a row at an offset.
    base = np.arange(24, dtype=np.float32).reshape(4, 6)
    np.testing.assert_array_equal(ckpt.tensors["extra.transposed"], base.T)
    np.testing.assert_array_equal(ckpt.tensors["extra.row"], base[2])
    assert ckpt.tensors["extra.bfloat16"].dtype == np.float32  # bfloat16 read as float32


def test_a_checkpoint_written_without_pytorch_reads_back(tmp_path):
    arrays = {"a.weight": np.arange(6, dtype=np.float32).reshape(2, 3), "b": np.ones(0)}
    ckpt = release.read_checkpoint(rf.write_state_dict(tmp_path / "x.pth", arrays))
    assert list(ckpt.tensors) == ["a.weight", "b"]
    np.testing.assert_array_equal(ckpt.tensors["a.weight"], arrays["a.weight"])


def _with_pickle(tmp_path: Path, edit) -> Path:
    """The fixture with its data.pkl passed through `edit`."""
    out = tmp_path / "edited.pth"
    with zipfile.ZipFile(TINY) as src, zipfile.ZipFile(out, "w") as dst:
        for info in src.infolist():
            data = src.read(info)
            dst.writestr(info, edit(data) if info.filename.endswith("data.pkl") else data)
    return out


@pytest.mark.parametrize(
    ("original", "injected", "named"),
    [
        (b"ctorch._utils\n_rebuild_tensor_v2\n", b"cos\nsystem\n", "os.system"),
        (b"ccollections\nOrderedDict\n", b"cbuiltins\neval\n", "builtins.eval"),
        (b"ctorch\nFloatStorage\n", b"ctorch\nTensor\n", "torch.Tensor"),
    ],
)
def test_a_forbidden_class_is_refused_before_anything_is_built(tmp_path, original, injected, named):
    def edit(data: bytes) -> bytes:
        assert original in data
        return data.replace(original, injected, 1)

    path = _with_pickle(tmp_path, edit)
    with pytest.raises(ValueError, match=named) as err:
        release.read_checkpoint(path)
    assert "\n" not in str(err.value) and str(path) in str(err.value)


def test_legacy_truncated_and_foreign_files_are_refused_in_one_line(tmp_path):
    with pytest.raises(ValueError, match="legacy.*torch.save") as err:
        release.read_checkpoint(FIXTURE / "tiny_legacy.pth")
    assert "\n" not in str(err.value)
    cut = tmp_path / "cut.pth"
    cut.write_bytes(TINY.read_bytes()[: TINY.stat().st_size // 2])
    with pytest.raises(ValueError, match="truncated"):
        release.read_checkpoint(cut)
    other = tmp_path / "other.pth"
    other.write_text("hello")
    with pytest.raises(ValueError, match="not a PyTorch zip checkpoint"):
        release.read_checkpoint(other)
    with pytest.raises(FileNotFoundError, match="missing.pth"):
        release.read_checkpoint(tmp_path / "missing.pth")
    # A storage file shorter than its record says.
    with zipfile.ZipFile(TINY) as z:
        entries = {i.filename: z.read(i) for i in z.infolist()}
    entries["tiny_state_dict/data/1"] = b"\x00" * 4
    with zipfile.ZipFile(tmp_path / "short.pth", "w") as z:
        for name, data in entries.items():
            z.writestr(name, data)
    with pytest.raises(ValueError, match="damaged"):
        release.read_checkpoint(tmp_path / "short.pth")


class _Evil:
    def __reduce__(self):
        return (subprocess.call, (["false"],))


def test_options_admit_only_an_argparse_namespace(tmp_path):
    options = rf.release_options()
    path = rf.write_options(tmp_path / "opt.pickle", options)
    assert release.read_options(path) == options
    evil = tmp_path / "evil.pickle"
    evil.write_bytes(pickle.dumps(_Evil()))
    with pytest.raises(ValueError, match="subprocess.call"):
        release.read_options(evil)
    plain = tmp_path / "dict.pickle"
    plain.write_bytes(pickle.dumps({"nkeypoints": 24}))
    with pytest.raises(ValueError, match="not an argparse.Namespace"):
        release.read_options(plain)


def test_reading_never_imports_torch():
    code = (
        "import sys; from nmjax import release; "
        f"release.read_checkpoint({str(TINY)!r}); assert 'torch' not in sys.modules"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


# --- layout conversions on hand cases (PyTorch's documented conventions) -----------------------


def _one_hot(shape, index) -> np.ndarray:
    w = np.zeros(shape, np.float32)
    w[index] = 1.0
    return w


def _conv_of(kernel: np.ndarray, **kwargs) -> blocks.Conv3D:
    k = kernel.shape[0]
    conv = blocks.Conv3D(kernel.shape[3], kernel.shape[4], k, rngs=nnx.Rngs(0), **kwargs)
    conv.kernel[...] = jnp.asarray(kernel)
    return conv


def _equations(jaxpr) -> list:
    """Every equation of `jaxpr` and of the jaxprs nested in its equations (custom VJPs, jits)."""
    found = []
    for eqn in jaxpr.eqns:
        found.append(eqn)
        for value in eqn.params.values():
            for sub in value if isinstance(value, (list, tuple)) else [value]:
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    found += _equations(inner)
    return found


# What each form of a 3x3x3 convolution with 2 input channels traces to: (spatial dims, input
# channels) of every convolution it runs. Winograd runs none: its channel mixing is one batched
# matmul over the 6^3 = 216 positions of a transformed tile.
CONVOLUTIONS_OF_FORM = {
    "native": [(3, 2)],  # XLA's 3D convolution
    "stacked": [(2, 3 * 2)],  # one 2D convolution, the 3 taps along x stacked on the channels
    "per_tap": [(2, 2)] * 3,  # one 2D convolution per tap along x
    "winograd": [],
}


@pytest.mark.parametrize("form", [*CONVOLUTIONS_OF_FORM, "auto"])
def test_conv3d_tap_lands_where_pytorch_puts_it(form):
    # Conv3d (padding 1): out[o, x] = sum W[o, i, a, b, c] in[i, x + a - 1, y + b - 1, z + c - 1].
    weight = _one_hot((2, 2, 3, 3, 3), (1, 0, 0, 1, 2))  # (out, in, kd, kh, kw)
    conv = _conv_of(release.conv_kernel(weight), evaluation=conv_kernels.Evaluation(form=form))
    x = np.zeros((1, 8, 8, 8, 2), np.float32)
    x[0, 3, 3, 3, 0] = 1.0
    out = np.asarray(conv(jnp.asarray(x)))
    hits = np.argwhere(np.abs(out) > 1e-6)
    np.testing.assert_array_equal(hits, [[0, 3 - 0 + 1, 3 - 1 + 1, 3 - 2 + 1, 1]])
    # The case ran the form it names ("auto": the one `resolve` picks on this backend).
    resolved = conv_kernels.resolve(form, None, (8, 8, 8), 3, jnp.float32)
    assert form == "auto" or resolved == form
    equations = _equations(jax.make_jaxpr(conv)(jnp.asarray(x)).jaxpr)
    convolutions = [
        (eqn.invars[0].aval.ndim - 2, eqn.invars[0].aval.shape[-1])
        for eqn in equations
        if eqn.primitive.name == "conv_general_dilated"
    ]
    assert convolutions == CONVOLUTIONS_OF_FORM[resolved], (form, resolved)
    tile_matmuls = [
        eqn
        for eqn in equations
        if eqn.primitive.name == "dot_general" and eqn.invars[0].aval.shape[0] == 6**3
    ]
    assert bool(tile_matmuls) == (resolved == "winograd"), (form, resolved)


def test_strided_and_transposed_taps_land_where_pytorch_puts_them():
    # Conv3d kernel 2 stride 2: out[o, x] = sum W[o, i, a, b, c] in[i, 2x + a, 2y + b, 2z + c].
    pool = blocks.Conv3D(2, 2, 2, 2, rngs=nnx.Rngs(0))
    pool.kernel[...] = jnp.asarray(release.conv_kernel(_one_hot((2, 2, 2, 2, 2), (0, 1, 1, 0, 1))))
    x = np.zeros((1, 8, 8, 8, 2), np.float32)
    x[0, 3, 2, 5, 1] = 1.0
    hits = np.argwhere(np.abs(np.asarray(pool(jnp.asarray(x)))) > 1e-6)
    np.testing.assert_array_equal(hits, [[0, 1, 1, 2, 0]])
    # ConvTranspose3d kernel 2 stride 2: out[o, 2x + a, 2y + b, 2z + c] += W[i, o, a, b, c] in[i].
    up = blocks.Conv3D(2, 2, 2, 2, transpose=True, rngs=nnx.Rngs(0))
    weight = _one_hot((2, 2, 2, 2, 2), (1, 0, 1, 0, 1))  # (in, out, kd, kh, kw)
    up.kernel[...] = jnp.asarray(release.conv_transpose_kernel(weight))
    x = np.zeros((1, 4, 4, 4, 2), np.float32)
    x[0, 1, 2, 0, 1] = 1.0
    hits = np.argwhere(np.abs(np.asarray(up(jnp.asarray(x)))) > 1e-6)
    np.testing.assert_array_equal(hits, [[0, 2 * 1 + 1, 2 * 2 + 0, 2 * 0 + 1, 0]])
    # The 1x1x1 fusion conv (2 -> 1) as an nnx.Linear kernel: channel 1 of the input.
    kernel = release.pointwise_kernel(_one_hot((1, 2, 1, 1, 1), (0, 1, 0, 0, 0)))
    np.testing.assert_array_equal(np.array([[3.0, 5.0]]) @ kernel, [[5.0]])


def _torch_gru(x, h, w_ih, w_hh, b_ih, b_hh):
    """nn.GRUCell as PyTorch documents it, the gates stacked r, z, n."""
    hidden = h.shape[-1]
    gi, gh = x @ w_ih.T + b_ih, h @ w_hh.T + b_hh
    i_r, i_z, i_n = np.split(gi, 3, axis=-1)
    h_r, h_z, h_n = np.split(gh, 3, axis=-1)
    r = 1 / (1 + np.exp(-(i_r + h_r)))
    z = 1 / (1 + np.exp(-(i_z + h_z)))
    n = np.tanh(i_n + r * h_n)
    assert n.shape[-1] == hidden
    return (1 - z) * n + z * h


def _gru(w_ih, w_hh, b_ih, b_hh) -> GRUCell:
    cell = GRUCell(w_ih.shape[1], w_hh.shape[1], rngs=nnx.Rngs(0))
    cell.input_kernel[...] = jnp.asarray(release.linear_kernel(w_ih))
    cell.hidden_kernel[...] = jnp.asarray(release.linear_kernel(w_hh))
    cell.input_bias[...] = jnp.asarray(b_ih)
    cell.hidden_bias[...] = jnp.asarray(b_hh)
    return cell


def test_gru_gates_and_both_biases_map_onto_pytorchs_cell():
    rng = np.random.default_rng(0)
    i, hidden = 5, 4
    w_ih, w_hh = rng.normal(size=(3 * hidden, i)), rng.normal(size=(3 * hidden, hidden))
    b_ih, b_hh = rng.normal(size=3 * hidden), rng.normal(size=3 * hidden)
    x, h = rng.normal(size=(2, i)), rng.normal(size=(2, hidden))
    cell = _gru(*(a.astype(np.float32) for a in (w_ih, w_hh, b_ih, b_hh)))
    out = np.asarray(cell(jnp.asarray(h, jnp.float32), jnp.asarray(x, jnp.float32)))
    np.testing.assert_allclose(out, _torch_gru(x, h, w_ih, w_hh, b_ih, b_hh), atol=1e-5)
    # Hand case: only b_hz (the second third of bias_hh) large -> z = 1 -> h' = h, whatever n.
    zeros = np.zeros((3 * hidden,), np.float32)
    b_hh = zeros.copy()
    b_hh[hidden : 2 * hidden] = 50.0
    cell = _gru(w_ih.astype(np.float32), w_hh.astype(np.float32), zeros, b_hh)
    out = np.asarray(cell(jnp.asarray(h, jnp.float32), jnp.asarray(x, jnp.float32)))
    np.testing.assert_allclose(out, h, atol=1e-6)
    # Only b_hn (the last third) and r = sigmoid(0): n = tanh(W_in x + 0.5 * (W_hn h + b_hn)).
    b_hh = zeros.copy()
    b_hh[2 * hidden :] = 3.0
    cell = _gru(w_ih.astype(np.float32), w_hh.astype(np.float32), zeros, b_hh)
    out = np.asarray(cell(jnp.asarray(h, jnp.float32), jnp.asarray(x, jnp.float32)))
    np.testing.assert_allclose(out, _torch_gru(x, h, w_ih, w_hh, zeros, b_hh), atol=1e-5)


def test_offsets_are_normalised_as_the_release_uses_them():
    p = np.array([[3.0, 0.0, 4.0], [0.0, 0.0, 0.0]], np.float32)
    np.testing.assert_allclose(release.offset_directions(p), [[0.6, 0.0, 0.8], [0, 0, 0]])


# --- the map at the release's sizes -------------------------------------------------------------


@pytest.fixture(scope="module")
def released():
    """Random tensors named and shaped as aist_state_dict.tsv, mapped onto networks built from
    aist_options.json."""
    shapes = rf.release_shapes()
    tensors = rf.random_tensors(shapes)
    widths = release.network_widths(tensors)
    skel, dyn = release.configs_from_options(rf.release_options(), widths, "imported")
    detector, dynamics, skeleton = release.build_networks(tensors, skel, dyn)
    return shapes, tensors, skel, dyn, detector, dynamics, skeleton


def test_the_map_covers_every_release_tensor_with_its_shape(released):
    shapes, tensors, skel, dyn, detector, dynamics, _ = released
    assert len(shapes) == 337
    expected = release.expected_tensors(detector, release.detector_entries(detector))
    expected |= release.expected_tensors(dynamics, release.dynamics_entries(dynamics))
    assert expected == shapes
    assert skel.model.channels == 128 and skel.model.hourglass_channels == (32, 48, 72)
    assert (skel.model.num_keypoints, skel.model.grid, skel.data.sample_rate) == (24, 64, 2)
    assert (dyn.model.latent, dyn.model.hidden, dyn.model.mlp, dyn.data.frames) == (
        128,
        512,
        128,
        20,
    )
    assert dyn.kl_weight == 0.003 and skel.weights.complex == 0.01 and skel.weights.vol == 10.0


def test_every_tensor_fills_the_networks_and_the_counts_agree(released):
    _, tensors, _, dyn, detector, dynamics, skeleton = released

    def count(model):
        return sum(int(np.prod(x.shape)) for x in jax.tree.leaves(nnx.state(model)))

    det_values = sum(a.size for n, a in tensors.items() if n.startswith("kypt_detector."))
    dyn_values = sum(a.size for n, a in tensors.items() if n.startswith("dyna_module."))
    assert (det_values, dyn_values) == (8_557_044, 1_529_971)  # shared/release/README.md
    assert count(detector) == det_values
    assert count(dynamics) == dyn_values  # every value, the GRU's two bias vectors included
    # Values landed where the map says, each with its layout.
    t = tensors
    conv = "kypt_detector.vox_to_kypt.extract_features.4.decoder_res2.res_branch.3.weight"
    np.testing.assert_array_equal(
        detector.features.hourglass.up_res[1].conv2.kernel[...], t[conv].transpose(2, 3, 4, 1, 0)
    )
    up = "kypt_detector.vox_to_kypt.extract_spatio_temporal_features.4.decoder_upsample1.block.0"
    np.testing.assert_array_equal(
        detector.st_features.hourglass.up[2].conv.kernel[...],
        t[f"{up}.weight"].transpose(2, 3, 4, 0, 1),
    )
    np.testing.assert_array_equal(
        detector.st_features.hourglass.up[2].norm.scale[...],
        t[
            "kypt_detector.vox_to_kypt.extract_spatio_temporal_features.4.decoder_upsample1.block.1"
            ".weight"
        ],
    )
    np.testing.assert_array_equal(detector.affinity_params[...], t["kypt_detector.affinity_params"])
    gn = "kypt_detector.kypt_to_vox.decode_voxel_from_combined_representation.9.bias"
    np.testing.assert_array_equal(detector.decoder.up2.layers[0].norm.bias[...], t[gn])
    # The GRU's four gate biases (and b_in, b_hn) one to one.
    b_ih, b_hh = t["dyna_module.kypt_rnn_cell.bias_ih"], t["dyna_module.kypt_rnn_cell.bias_hh"]
    np.testing.assert_array_equal(dynamics.rnn.input_bias[...], b_ih)
    np.testing.assert_array_equal(dynamics.rnn.hidden_bias[...], b_hh)
    np.testing.assert_array_equal(
        dynamics.initial_hidden[...], t["dyna_module.init_kypt_rnn_state"][0]
    )
    norms = np.linalg.norm(np.asarray(dynamics.directions[...]), axis=-1)
    np.testing.assert_allclose(norms, 1.0, rtol=1e-5)
    np.testing.assert_array_equal(
        dynamics.rotation_decoder.out.bias[...], t["dyna_module.joint_matrix_decoder.2.bias"]
    )
    assert dynamics.parents == skeleton.parents and len(skeleton.parents) == 24


def _leaky(x):
    return np.where(x > 0, x, 0.01 * x)


def test_dynamics_heads_compute_the_releases_mlps(released):
    """Posterior and decoders as the release's nn.Sequential (Linear, LeakyReLU, Linear): the
    Linear transposes give the same outputs."""
    _, t, _, dyn, _, dynamics, _ = released
    rng = np.random.default_rng(1)
    hz = rng.normal(size=(2, dyn.model.hidden + dyn.model.latent)).astype(np.float32)

    def release_mlp(name, x):
        p = "dyna_module." + name
        hidden = _leaky(x @ t[f"{p}.0.weight"].T + t[f"{p}.0.bias"])
        return hidden @ t[f"{p}.2.weight"].T + t[f"{p}.2.bias"]

    rot = np.asarray(dynamics.rotation_decoder(jnp.asarray(hz)))
    np.testing.assert_allclose(rot, release_mlp("joint_matrix_decoder", hz), atol=1e-4)
    glob = np.asarray(dynamics.global_decoder(jnp.asarray(hz)))
    np.testing.assert_allclose(glob, release_mlp("root_intensity_decoder", hz), atol=1e-4)


def test_leftover_missing_and_mismatched_tensors_are_named(released):
    shapes, tensors, skel, dyn, *_ = released
    extra = {**tensors, "kypt_detector.extra.weight": np.zeros(3, np.float32)}
    with pytest.raises(ValueError, match=r"kypt_detector\.extra\.weight"):
        release.build_networks(extra, skel, dyn)
    gone = {k: v for k, v in tensors.items() if k != "dyna_module.kypt_rnn_cell.bias_hh"}
    with pytest.raises(ValueError, match=r"lacks dyna_module\.kypt_rnn_cell\.bias_hh"):
        release.build_networks(gone, skel, dyn)
    name = "kypt_detector.vox_to_kypt.extract_heatmaps_from_features.0.weight"
    bent = {**tensors, name: np.zeros((20, 128, 1, 1, 1), np.float32)}
    with pytest.raises(ValueError, match=r"shapes disagree.*\(20, 128, 1, 1, 1\).*heat") as err:
        release.build_networks(bent, skel, dyn)
    assert "(24, 128, 1, 1, 1)" in str(err.value)
    # Options whose K is not the tensors'.
    skel20, dyn20 = release.configs_from_options(
        rf.release_options(nkeypoints=20), release.network_widths(tensors), "x"
    )
    with pytest.raises(ValueError, match="affinity_params") as err:
        release.build_networks(tensors, skel20, dyn20)
    assert "opt.pickle" in str(err.value) and "\n" not in str(err.value)


def test_options_of_another_network_are_refused():
    widths = release.Widths(128, (32, 48, 72), 128)
    with pytest.raises(ValueError, match="dyna_module='SVRNN'"):
        release.configs_from_options(rf.release_options(dyna_module="SVRNN"), widths, "x")
    with pytest.raises(ValueError, match="'nope'"):
        release.configs_from_options(rf.release_options(dataset="nope"), widths, "x")
    options = rf.release_options()
    del options["nkeypoints"]
    with pytest.raises(ValueError, match="nkeypoints"):
        release.configs_from_options(options, widths, "x")


# --- import-release end to end on a small checkpoint ---------------------------------------------

K = 6
SMALL = {
    "dataset": "synth-arm",
    "grid_size": 32,
    "nkeypoints": K,
    "nlatent_kypt": 4,
    "nhidden_kypt": 16,
    "Ttot": 6,
    "Tcond": 2,
    "nbatch": 4,
    "sample_rate": 1,
}


def small_checkpoint(folder: Path) -> tuple[Path, Path]:
    """A checkpoint of the release's structure at small sizes (G = 32, C = 8, hourglass 8, K = 6,
    D_z = 4, D_h = 16, MLP 8), random values, in PyTorch's zip format; and its opt.pickle."""
    from nmjax.models.detector import KeypointDetector
    from nmjax.models.dynamics import Dynamics

    options = rf.release_options(**SMALL)
    skel, dyn = release.configs_from_options(options, release.Widths(8, (8, 8, 8), 8), "x")
    detector = KeypointDetector(skel.model, rngs=nnx.Rngs(0))
    chain = tuple(max(k - 1, 0) for k in range(K))
    dynamics = nnx.eval_shape(lambda: Dynamics(dyn.model, chain, tuple(range(K)), rngs=nnx.Rngs(0)))
    shapes = release.expected_tensors(detector, release.detector_entries(detector))
    shapes |= release.expected_tensors(dynamics, release.dynamics_entries(dynamics))
    tensors = rf.random_tensors(shapes, seed=3)
    pth = rf.write_state_dict(folder / "small.pth", tensors)
    return pth, rf.write_options(folder / "opt.pickle", options)


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """A folder with the small checkpoint, its options, a 3-sequence synth-arm set under
    data/synth-arm (the configs' default root, relative to the folder) and one of its sequences
    as a point-sequence file."""
    from nmjax.data import synthetic
    from nmjax.data.datasets import load_sequences

    root = tmp_path_factory.mktemp("release")
    pth, opt = small_checkpoint(root)
    data = synthetic.generate(
        "synth-arm",
        root / "data" / "synth-arm",
        num_sequences=3,
        frames=24,
        points=800,
        progress=False,
    )
    seq = load_sequences("synth-arm", "test", data)[0]
    np.save(root / "motion.npy", np.asarray(seq.vertices, np.float32))
    return root, pth, opt


@pytest.fixture(scope="module")
def imported(small):
    """`nmjax import-release` of the small checkpoint into <root>/imported, the keypoint
    statistics from the point-sequence file; (root, skel run, dyn run, printed lines)."""
    import contextlib
    import os

    from nmjax import cli

    root, pth, opt = small
    here = os.getcwd()
    os.chdir(root)  # run folders name each other by the paths given, relative to here
    argv = ["import-release", str(pth), "--options", str(opt), "--run", "imported"]
    try:
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            code = cli.main([*argv, "--example", "motion.npy"])
    finally:
        os.chdir(here)
    assert code == 0
    return root, root / "imported" / "skel", root / "imported" / "dyn", out.getvalue()


def test_import_writes_two_run_folders_of_the_imported_values(small, imported, monkeypatch):
    from nmjax import keypoints, run_folder
    from nmjax.config import DynTrainConfig, SkelTrainConfig
    from nmjax.skeleton import extract_skeleton
    from nmjax.train import trained
    from nmjax.train.trained import Detector

    _, pth, opt = small
    root, skel_run, dyn_run, printed = imported
    monkeypatch.chdir(root)
    assert "imported/skel" in printed and "imported/dyn" in printed
    assert sorted(p.name for p in root.iterdir() if p.name.startswith(".")) == []
    skel = run_folder.load_config(skel_run, SkelTrainConfig)
    dyn = run_folder.load_config(dyn_run, DynTrainConfig)
    assert (skel.model.num_keypoints, skel.model.channels, skel.data.grid) == (K, 8, 32)
    assert skel.model.hourglass_channels == (8, 8, 8) and skel.data.name == "synth-arm"
    assert dyn.skel_run == "imported/skel" and dyn.data.frames == 6 and dyn.model.hidden == 16
    for name in ("affinity.npy", "keypoint_stats.npz", "skeleton.json", "release.json"):
        assert (skel_run / name).is_file(), name
    ckpt = release.read_checkpoint(pth)
    record = json.loads((dyn_run / "release.json").read_text())
    assert record["sha256"] == ckpt.sha256 and record["options"] == release.read_options(opt)
    assert "commit" in record["provenance"] and record["tensors"] == len(ckpt.tensors)
    # The imported values, restored through the run-folder readers; the skeleton is Algorithm 1
    # on the imported affinity.
    tensors = ckpt.tensors
    detector = Detector.load(skel_run)
    restored = nnx.merge(detector.graphdef, detector.state)
    logits = tensors["kypt_detector.affinity_params"]
    np.testing.assert_array_equal(restored.affinity_params[...], logits)
    tree = extract_skeleton(np.asarray(keypoints.affinity_from_params(jnp.asarray(logits))))
    assert run_folder.read_skeleton(skel_run).parents == tree.parents
    model = trained.restore_dynamics(dyn_run)
    np.testing.assert_array_equal(
        model.initial_hidden[...], tensors["dyna_module.init_kypt_rnn_state"][0]
    )
    assert model.parents == tree.parents


def test_generate_and_retarget_take_a_point_sequence_file(imported, monkeypatch):
    import trimesh

    from nmjax import cli, tasks

    root, _, dyn_run, _ = imported
    monkeypatch.chdir(root)
    run = str(dyn_run)
    # Clips of 10 frames, the import's crop: one compilation of the detector serves them all.
    gen = ["generate", "--run", run, "--source-file", "motion.npy", "--cond", "10", "--gen", "2"]
    assert cli.main([*gen, "--samples", "2", "--source-rate", "2", "--out", "g"]) == 0
    with np.load("g/generate.npz") as z:
        assert z["keypoints"].shape == (1, 2, 12, K, 4) and np.all(np.isfinite(z["keypoints"]))
        assert str(z["names"][0]) == "motion" and list(z["observed_frames"]) == [10]
    box = trimesh.creation.box(extents=(0.2, 0.3, 1.0))
    box.export("box.obj")
    re = ["retarget", "--run", run, "--target", "box.obj", "--source-file", "motion.npy"]
    assert cli.main([*re, "--frames", "10", "--points", "500"]) == 0
    out = dyn_run / "retarget-box"
    assert tasks.read_retarget(out)["vertices"].shape == (10, 8, 3)
    assert str(np.load(out / "retarget.npz")["source"]) == "motion"


@pytest.mark.slow
def test_interpolate_and_decoded_generation_take_a_point_sequence_file(imported, monkeypatch):
    from nmjax import cli

    root, _, dyn_run, _ = imported
    monkeypatch.chdir(root)
    run = str(dyn_run)
    interp = ["interpolate", "--run", run, "--source-file", "motion.npy", "--gap", "9"]
    assert cli.main([*interp, "--trajectories", "2", "--out", "in"]) == 0
    with np.load("in/interpolate.npz") as z:
        assert z["Ours"].shape == (1, 10, K, 4)
    gen = ["generate", "--run", run, "--source-file", "motion.npy", "--cond", "10", "--gen", "2"]
    assert cli.main([*gen, "--samples", "1", "--voxels", "--out", "gv"]) == 0
    with np.load("gv/voxels.npz") as z:
        assert z["voxels"].shape == (1, 1, 12, 32, 32, 32)


@pytest.mark.slow
def test_evaluate_and_view_accept_the_imported_runs(small, monkeypatch):
    """Imported with the keypoint statistics of the dataset's test split (the default), then
    the phase-1 and phase-2 evaluation and the viewer's readers."""
    from nmjax import cli, view

    root, pth, opt = small
    monkeypatch.chdir(root)  # the dataset's default root, data/synth-arm, is relative
    argv = ["import-release", str(pth), "--options", str(opt), "--run", "from-data"]
    assert cli.main(argv) == 0
    skel_run, dyn_run = Path("from-data/skel"), Path("from-data/dyn")
    stats = np.load(skel_run / "keypoint_stats.npz")
    assert stats["example_voxels"].shape == (32, 32, 32) and stats["intensities"].shape == (K,)
    assert cli.main(["export-keypoints", "--run", str(skel_run)]) == 0
    assert cli.main(["evaluate", "--run", str(skel_run), "--max-crops", "1"]) == 0
    rates = ["--rates", "2", "--max-segments", "1", "--trajectories", "2", "--max-crops", "1"]
    assert cli.main(["evaluate", "--run", str(dyn_run), *rates]) == 0
    assert (dyn_run / "eval" / "results.json").is_file()
    assert view.folder_kind(skel_run) == "skel" and view.folder_kind(dyn_run) == "dyn"
    assert view.read_phase1(skel_run).keypoints and view.read_phase2(dyn_run).model


def test_point_file_clip_is_the_releases_crop(imported):
    """Frames 0, r, 2r, ... of the file, one bounding box over them, one crop through the
    detector."""
    from nmjax import tasks
    from nmjax.data import meshes
    from nmjax.data.normalize import normalize_sequence
    from nmjax.data.voxelize import voxelize
    from nmjax.train.trained import Detector

    root, skel_run, _, _ = imported
    detector = Detector.load(skel_run)
    points = np.load(root / "motion.npy")
    keypoints, voxels = tasks.point_file_keypoints(detector, root / "motion.npy", 10, 2)
    clip, _ = normalize_sequence(points[0:19:2])
    np.testing.assert_array_equal(voxels, voxelize(clip, 32))
    assert keypoints.shape == (10, K, 4) and np.all(np.isfinite(keypoints))
    with pytest.raises(ValueError, match="24 frames; 10 frames every 3 need 28"):
        tasks.point_file_keypoints(detector, root / "motion.npy", 10, 3)
    bad = root / "flat.npy"
    np.save(bad, np.zeros((4, 3)))
    with pytest.raises(ValueError, match=r"shape \(4, 3\)"):
        meshes.load_point_sequence(bad)


def test_import_refuses_an_existing_folder_and_writes_nothing_on_failure(
    small, tmp_path, monkeypatch
):
    root, pth, opt = small
    monkeypatch.chdir(tmp_path)  # no data/synth-arm here
    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / "keep.txt").write_text("mine")
    with pytest.raises(ValueError, match="--overwrite"):
        release.import_release(pth, opt, taken, progress=False)
    # --overwrite replaces an earlier import only, never a folder of something else.
    with pytest.raises(ValueError, match="not a folder `nmjax import-release` wrote"):
        release.import_release(pth, opt, taken, overwrite=True, progress=False)
    assert [p.name for p in taken.iterdir()] == ["keep.txt"]
    # No dataset and no --example: refused after reading, before writing anything.
    with pytest.raises(FileNotFoundError, match="--example"):
        release.import_release(pth, opt, tmp_path / "new", progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken"]
    # --example gives the keypoint statistics; --overwrite replaces the earlier import.
    example = root / "motion.npy"
    skel_run, _ = release.import_release(pth, opt, "new", example=example, progress=False)
    assert skel_run == Path("new/skel") and (skel_run / "skeleton.json").is_file()
    (skel_run / "mark").write_text("old")
    release.import_release(pth, opt, "new", overwrite=True, example=example, progress=False)
    assert not (skel_run / "mark").exists() and (skel_run / "skeleton.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["new", "taken"]


def test_resuming_an_imported_run_points_to_init_from(imported, monkeypatch, capsys):
    """The imported folders hold weights and an untouched optimizer (checkpoint 0): --resume is
    refused in one line, before any data is read, naming --init-from."""
    from nmjax import cli

    root, _, _, _ = imported
    monkeypatch.chdir(root)
    for command, run in (("train-skel", "imported/skel"), ("train-dyn", "imported/dyn")):
        assert cli.main([command, "--run", run, "--resume", "--no-progress"]) == 2
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1, lines
        assert "no optimizer state" in lines[0] and f"--init-from {run}" in lines[0], lines
