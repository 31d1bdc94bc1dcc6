"""`nmjax bench`, the optimisation benchmark script at tiny shapes, and bfloat16 convolutions."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from experiment_scripts import load_experiment
from flax import nnx

from nmjax import bench, losses
from nmjax.cli import main as nmjax_main
from nmjax.cli.bench import parse_args
from nmjax.config import skel_preset
from nmjax.models.blocks import Conv3D
from nmjax.models.conv_kernels import Evaluation
from nmjax.models.detector import KeypointDetector, check_detector_config

ROW_KEYS = {
    "phase",
    "preset",
    "B",
    "T",
    "K",
    "compute_dtype",
    "steps",
    "steps_per_s",
    "frames_per_s",
    "load_s_per_step",
    "compute_s_per_step",
    "compile_s",
    "memory",
    "data",
}


@pytest.fixture(scope="module")
def arm_root(tmp_path_factory):
    from nmjax.data import synthetic

    root = tmp_path_factory.mktemp("data")
    return synthetic.generate(
        "synth-arm", root, num_sequences=3, frames=12, points=1500, progress=False
    )


def test_bench_main_writes_rows_for_both_phases_and_the_detector(arm_root, tmp_path, capsys):
    out = tmp_path / "bench.json"
    argv = ["--preset", "tiny", "--steps", "2", "--warmup", "0", "--compute-dtype", "bfloat16"]
    argv += ["--set", f"skel:data.root={arm_root}", "--set", "dyn:data.batch_size=2"]
    argv += ["--set", "skel:data.grid=8", "--set", "skel:model.grid=8"]  # fewer ops to compile
    assert nmjax_main(["bench", *argv, "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert list(result)[0] == "provenance" and result["provenance"]["metrics"] == bench.METRICS
    assert {"commit", "dirty", "cpu", "date"} <= set(result["provenance"])
    env = result["environment"]
    assert env["jax"] == jax.__version__ and env["cpu_count"] >= 1 and env["device_count"] >= 1
    assert {"devices", "backend", "load_avg_1min"} <= set(env)
    skel_row, dyn_row, detect_row = result["rows"]
    for row in (skel_row, dyn_row, detect_row):
        assert ROW_KEYS <= set(row)
        assert row["steps"] == 2
        for key in ("steps_per_s", "frames_per_s", "compute_s_per_step", "compile_s"):
            assert row[key] > 0, key
        assert row["frames_per_s"] == pytest.approx(row["steps_per_s"] * row["B"] * row["T"])
        total = row["load_s_per_step"] + row["compute_s_per_step"]
        assert row["steps_per_s"] == pytest.approx(1 / total)
        mem = row["memory"]
        assert all(mem[k] >= 0 for k in bench.MEMORY_KEYS) and mem["argument_bytes"] > 0
        assert mem.get("peak_bytes_in_use", mem.get("peak_rss_bytes", 0)) > 0
    assert (skel_row["phase"], skel_row["compute_dtype"], skel_row["B"]) == ("skel", "bfloat16", 2)
    assert skel_row["conv_form"] == "stacked"  # the tiny preset's model.conv_form, recorded with it
    assert skel_row["load_s_per_step"] > 0
    assert (dyn_row["phase"], dyn_row["B"]) == ("dyn", 2)
    assert dyn_row["load_s_per_step"] > 0  # the batch cut on the host
    # The detector on phase-2 crops: the phase-1 preset's network, the phase-2 preset's T.
    assert (detect_row["phase"], detect_row["G"], detect_row["B"], detect_row["T"]) == (
        "detect",
        8,
        skel_row["B"],
        6,
    )
    assert detect_row["load_s_per_step"] > 0  # normalising and voxelising the crops
    table = capsys.readouterr().out
    assert "steps/s" in table and "tiny/nm" in table


def test_each_job_argv_reproduces_its_row_config():
    args = parse_args(
        ["--preset", "tiny", "cpu", "--dyn-model", "nm", "vrnn", "--set", "skel:seed=4"]
        + ["--set", "dyn:data.batch_size=8", "--compute-dtype", "bfloat16", "--keypoints", "7"]
    )
    todo = bench.jobs(args)
    assert todo == [
        ("skel", "tiny", None),
        ("skel", "cpu", None),
        ("dyn", "tiny", "nm"),
        ("dyn", "tiny", "vrnn"),
        ("dyn", "cpu", "nm"),
        ("dyn", "cpu", "vrnn"),
        ("detect", "tiny", None),
        ("detect", "cpu", None),
    ]
    for phase, preset, model in todo:
        one = parse_args(bench.job_argv(args, phase, preset, model))
        assert bench.jobs(one) == [(phase, preset, model)]
        assert bench.configs(one, phase, preset) == bench.configs(args, phase, preset)
        assert (one.steps, one.warmup, one.keypoints) == (args.steps, args.warmup, 7)
    assert bench.configs(args, "skel", "tiny").model.compute_dtype == "bfloat16"
    assert bench.configs(args, "detect", "tiny") == bench.configs(args, "skel", "tiny")
    assert bench.configs(args, "dyn", "cpu").data.batch_size == 8
    # The batch has one spelling in both phases: an unprefixed item sets both.
    both = parse_args(["--preset", "cpu", "--set", "data.batch_size=4"])
    assert {bench.configs(both, p, "cpu").data.batch_size for p in ("skel", "dyn")} == {4}


def test_split_overrides_by_phase():
    items = ["skel:model.channels=16", "dyn:data.batch_size=8", "seed=3"]
    assert bench._split_overrides(items, "skel") == ["model.channels=16", "seed=3"]
    assert bench._split_overrides(items, "dyn") == ["data.batch_size=8", "seed=3"]


def test_bench_refuses_bad_override(capsys):
    assert nmjax_main(["bench", "--phase", "dyn", "--preset", "tiny", "--set", "dyn:nope=1"]) == 2
    err = capsys.readouterr().err
    assert "nope" in err and len(err.strip().splitlines()) == 1


def test_optimisation_benchmark_times_the_model_against_the_plain_forms(tmp_path, capsys):
    """experiments/bench_optimisations.py at tiny shapes: one row per case (a)-(d), (f), (g),
    each pair computing the same function ((e) needs a dataset on disk and is left out)."""
    module = load_experiment("bench_optimisations.py")
    out = tmp_path / "opt.json"
    cases = ["a", "b", "c", "d", "f", "g"]
    argv = ["--preset", "tiny", "--only", *cases, "--repeats", "1", "--out", str(out)]
    assert module.main(argv) == 0
    result = json.loads(out.read_text())
    assert result["provenance"]["metrics"] == module.METRICS
    rows = result["rows"]
    # The whole-decoder row is "(a, g)": both optimisations are inside the decoder.
    expected = ["(a,", "(a)"] + ["(b)"] * 4 + ["(c)", "(f)"] + ["(g)"] * 2 + ["(d)"]
    assert [r["name"][:3] for r in rows] == expected
    for row in rows:
        assert row["grad_rel_diff"] < 1e-3 and row["value_rel_diff"] < 1e-4, row
        assert row["plain_s"] > 0 and row["fast_s"] > 0
    assert "speed-up" in capsys.readouterr().out


def test_conv3d_computes_in_bfloat16_and_returns_float32():
    conv = Conv3D(3, 4, 3, rngs=nnx.Rngs(0))
    x = jnp.asarray(np.random.default_rng(0).normal(size=(2, 6, 6, 6, 3)), jnp.float32)
    ref = conv(x)
    conv = Conv3D(3, 4, 3, evaluation=Evaluation("auto", "bfloat16"), rngs=nnx.Rngs(0))
    out = conv(x)
    assert out.dtype == jnp.float32 and conv.kernel[...].dtype == jnp.float32
    assert "bf16" in str(jax.make_jaxpr(conv)(x))
    assert not np.array_equal(out, ref)
    np.testing.assert_allclose(out, ref, atol=0.05 * float(jnp.max(jnp.abs(ref))))
    with pytest.raises(ValueError, match="model.compute_dtype"):
        Evaluation("auto", "float16")


def test_bfloat16_detector_close_to_float32_with_float32_params_and_losses():
    cfg = skel_preset("synth-arm", "tiny")
    f32 = KeypointDetector(cfg.model, rngs=nnx.Rngs(0))
    bf16_cfg = dataclasses.replace(cfg.model, compute_dtype="bfloat16")
    bf16 = KeypointDetector(bf16_cfg, rngs=nnx.Rngs(0))
    voxels = (np.random.default_rng(0).random((1, 4, 16, 16, 16)) > 0.7).astype(np.float32)
    (g32, s32), (g16, s16) = nnx.split(f32), nnx.split(bf16)

    @jax.jit
    def both(s32, s16, v):  # one compilation instead of two slow eager passes
        return nnx.merge(g32, s32)(v), nnx.merge(g16, s16)(v)

    ref, out = both(s32, s16, jnp.asarray(voxels))
    for name in ("recon", "heatmaps", "keypoints", "affinity"):
        assert out[name].dtype == jnp.float32, name
        np.testing.assert_allclose(out[name], ref[name], atol=0.1, err_msg=name)
    assert not np.array_equal(out["recon"], ref["recon"])
    assert {x.dtype for x in jax.tree.leaves(nnx.state(bf16, nnx.Param))} == {jnp.dtype("float32")}
    total, terms = losses.skeleton_loss({"voxels": voxels, **out}, cfg.weights)
    ref_total, _ = losses.skeleton_loss({"voxels": voxels, **ref}, cfg.weights)
    assert total.dtype == jnp.float32 and all(v.dtype == jnp.float32 for v in terms.values())
    np.testing.assert_allclose(total, ref_total, rtol=0.05)


def test_detector_config_refuses_unknown_compute_dtype():
    cfg = dataclasses.replace(skel_preset("synth-arm", "tiny").model, compute_dtype="half")
    with pytest.raises(ValueError, match="model.compute_dtype"):
        check_detector_config(cfg)
