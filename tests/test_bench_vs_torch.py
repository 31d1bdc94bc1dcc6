"""experiments/bench_vs_torch.py: the PyTorch twin computes nmjax's detector, and the script runs.

torch is optional (the `bench-torch` extra; CI does not install it): the tests that need it skip
without it, the missing-torch exit path is tested with torch hidden.
"""

from __future__ import annotations

import json
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from experiment_scripts import load_experiment
from flax import nnx
from tiny_runs import spread_convolutions

from nmjax import losses
from nmjax.config import skel_preset
from nmjax.config_io import apply_overrides
from nmjax.models.detector import KeypointDetector


def load_script(name: str = "bench_vs_torch"):
    return load_experiment("bench_vs_torch.py", name)


@pytest.fixture(scope="module")
def arm_root(tmp_path_factory):
    from nmjax.data import synthetic

    root = tmp_path_factory.mktemp("data")
    return synthetic.generate(
        "synth-arm", root, num_sequences=3, frames=12, points=1500, progress=False
    )


def test_without_torch_exits_2_with_the_install_hint(monkeypatch, capsys):
    for name in [m for m in sys.modules if m == "torch" or m.startswith("torch.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "torch", None)  # `import torch` now raises ImportError
    script = load_script("bench_vs_torch_without_torch")
    assert script.torch is None
    assert script.main(["--shape", "cpu", "--steps", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pip install -e '.[bench-torch]'" in err[0]


def test_named_shapes_are_the_issue_rows():
    script = load_script()
    args = script.parse_args(["--shape", "cpu", "paper-channels", "paper"])
    got = {name: script.shape_of(cfg) for name, _, cfg in script.rows_of(args)}
    expect = {
        "cpu": (32, 16, [16, 24, 32], 12, 2, 6),
        "paper-channels": (32, 128, [32, 48, 72], 12, 2, 10),
        "paper": (64, 128, [32, 48, 72], 28, 1, 10),
    }
    for name, (g, c, hg, k, b, t) in expect.items():
        s = got[name]
        assert (s["G"], s["C"], s["hourglass"], s["K"], s["B"], s["T"]) == (g, c, hg, k, b, t)
    default = script.rows_of(script.parse_args([]))
    assert [name for name, _, _ in default] == ["cpu", "paper-channels"]
    custom = script.rows_of(script.parse_args(["--preset", "default", "--set", "data.frames=4"]))
    assert [(n, p, cfg.data.frames) for n, p, cfg in custom] == [("preset:default", "default", 4)]
    with pytest.raises(SystemExit):
        script.parse_args(["--preset", "cpu", "--shape", "cpu"])


@pytest.mark.parametrize(("grid", "stride"), [(16, 4), (8, 2)])
def test_twin_computes_the_detector_and_its_loss(grid, stride):
    """Same parameter count, same outputs and loss terms, same gradients with nmjax's weights."""
    torch = pytest.importorskip("torch")
    script = load_script()
    overrides = [f"model.grid={grid}", f"data.grid={grid}", f"model.heatmap_stride={stride}"]
    cfg = apply_overrides(skel_preset("synth-arm", "tiny"), overrides)
    model_cfg = cfg.model
    detector = KeypointDetector(model_cfg, rngs=nnx.Rngs(0))
    # Weights of unit-ish scale instead of the release's 0.001 / 0.02, so that every layer,
    # both heatmap branches and the LeakyReLUs' negative sides are in play.
    spread_convolutions(detector)
    twin = script.TwinDetector(model_cfg)
    n_params = sum(int(p.size) for p in jax.tree.leaves(nnx.state(detector, nnx.Param)))
    assert script.twin_param_count(twin) == n_params == script.nmjax_param_count(model_cfg)
    assert script.copy_params(detector, twin) == len(list(twin.parameters()))

    b, t, k, g = 2, 3, model_cfg.num_keypoints, grid // stride
    voxels = (np.random.default_rng(0).random((b, t, grid, grid, grid)) < 0.2).astype(np.float32)

    def loss_fn(model):
        out = {"voxels": jnp.asarray(voxels), **model(jnp.asarray(voxels))}
        return losses.skeleton_loss(out, cfg.weights)[0], out

    (loss, out), grads = nnx.jit(nnx.value_and_grad(loss_fn, has_aux=True))(detector)
    theirs = twin(torch.from_numpy(voxels))
    assert theirs["recon"].shape == out["recon"].shape == (b, t, grid, grid, grid)
    assert theirs["keypoints"].shape == out["keypoints"].shape == (b, t, k, 4)
    assert out["heatmaps"].shape == (b, t, g, g, g, k)
    assert theirs["heatmaps"].shape == (b, t, k, g, g, g)
    heat = theirs["heatmaps"].detach().numpy().transpose(0, 1, 3, 4, 5, 2)
    np.testing.assert_allclose(heat, out["heatmaps"], atol=1e-4 * float(np.max(heat)))
    for key in ("recon", "keypoints", "affinity"):
        np.testing.assert_allclose(theirs[key].detach().numpy(), out[key], atol=1e-4, err_msg=key)
    total, terms = script.twin_loss(theirs, cfg.weights)
    ours = losses.skeleton_loss(out, cfg.weights)[1]
    for name, value in terms.items():
        np.testing.assert_allclose(float(value.detach()), ours[name], rtol=1e-4, atol=1e-7)
    np.testing.assert_allclose(float(total.detach()), loss, rtol=1e-5)

    total.backward()
    expected = script.in_twin_layout(grads, twin)
    for name, param in twin.named_parameters():
        want = expected[name]
        scale = float(np.max(np.abs(want))) + 1e-8
        np.testing.assert_allclose(param.grad.numpy(), want, atol=1e-3 * scale, err_msg=name)


def test_main_times_both_sides_and_writes_json(arm_root, tmp_path, capsys):
    pytest.importorskip("torch")
    script = load_script()
    out = tmp_path / "vs_torch.json"
    argv = ["--preset", "tiny", "--steps", "1", "--warmup", "0", "--threads", "1"]
    argv += ["--set", f"data.root={arm_root}", "--set", "data.grid=8", "--set", "model.grid=8"]
    assert script.main([*argv, "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["provenance"]["metrics"] == script.METRICS
    env = result["environment"]
    assert env["cpu_count"] >= 1 and env["torch_threads"] == 1 and env["torch"] and env["jax"]
    assert "load_avg_1min" in env
    (row,) = result["rows"]
    assert row["name"] == "preset:tiny" and (row["shape"]["G"], row["shape"]["B"]) == (8, 2)
    jax_side, torch_side = row["jax"], row["torch"]
    assert len(jax_side["step_s"]) == 1 and jax_side["median_s"] == jax_side["step_s"][0]
    assert jax_side["row"]["phase"] == "skel" and jax_side["row"]["steps"] == 1
    assert len(torch_side["step_s"]) == 1 and torch_side["median_s"] > 0
    assert torch_side["params"] == torch_side["nmjax_params"]
    assert row["ratio"] == pytest.approx(jax_side["median_s"] / torch_side["median_s"])
    table = capsys.readouterr().out
    assert "jax/torch" in table and "preset:tiny" in table
