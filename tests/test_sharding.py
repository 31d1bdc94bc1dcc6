"""Data parallelism (nmjax.train.parallel): sharded train steps of both phases against the
single-device step, refused batch sizes, host shards of the input pipeline, distributed flags.

The multi-device checks run this file as a script in a subprocess with two forced CPU devices
(XLA_FLAGS=--xla_force_host_platform_device_count=2), since the device count is fixed when the
backend starts; the script prints one JSON line of results that the tests read.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from tiny_configs import small_skel_config

from nmjax.config import dyn_preset

PARENTS = (0, 0, 1, 2, 1)  # phase-2 tree: root 0, chain 0-1-2-3 and branch 1-4
ORDER = (0, 1, 2, 3, 4)


def _dyn_cfg(batch_size: int = 4):
    cfg = dyn_preset("synth-arm", "tiny")  # trained on a fake phase-1 run without a detector
    return dataclasses.replace(
        cfg, data=dataclasses.replace(cfg.data, batch_size=batch_size, inputs="sequence")
    )


# --- the script (runs with two CPU devices) ----------------------------------------------------


def _compare_states(sharded, single, params_prefix: str, learning_rate: float, steps: int):
    """Asserts two train states agree (rtol 1e-4, atol 1e-5) except where a parameter's gradient
    is float noise; returns {"elements": compared, "noise": excused parameter elements}.

    A convolution bias followed by a normalisation has zero gradient in exact arithmetic; in
    floats it is noise whose sign depends on the order of the cross-device sum, and Adam turns it
    into a full step of `learning_rate` either way. An element that differs is excused only if
    its gradient is such noise (Adam's sqrt(nu) below 1e-6 of the largest in the state) and the
    difference is at most 2 * steps * learning_rate.
    """
    import jax

    def flat(tree):
        return {jax.tree_util.keystr(p): np.asarray(x) for p, x in jax.tree.leaves_with_path(tree)}

    flat1, flat2 = flat(single), flat(sharded)
    assert flat1.keys() == flat2.keys()
    # Adam's second moments, keyed like the parameters (`['nu']` or `.nu` then the same path).
    nus = {k: np.sqrt(v) for k, v in flat1.items() if "['nu']" in k or ".nu" in k}
    assert nus, "no Adam second moments found in the state"
    scale = max(float(v.max()) for v in nus.values())
    elements = noise = 0
    for key, desired in flat1.items():
        actual = flat2[key]
        elements += desired.size
        differs = ~np.isclose(actual, desired, rtol=1e-4, atol=1e-5)
        if differs.any() and key.startswith(params_prefix):
            rest = key[len(params_prefix) :]
            (nu,) = [v for k, v in nus.items() if k.endswith(("['nu']" + rest, ".nu" + rest))]
            excused = differs & (nu < 1e-6 * scale)
            excused &= np.abs(actual - desired) <= 2 * steps * learning_rate + 1e-6
            noise += int(excused.sum())
            actual, desired = actual[~excused], desired[~excused]
        np.testing.assert_allclose(actual, desired, rtol=1e-4, atol=1e-5, err_msg=key)
    return {"elements": elements, "noise": noise}


def _script_skel(workdir: Path) -> dict:
    import jax

    from nmjax.data import pipeline, synthetic
    from nmjax.train import checkpoints, parallel, skel

    root = synthetic.generate(
        "synth-arm", workdir / "data", num_sequences=2, frames=6, points=500, progress=False
    )
    cfg = small_skel_config(root, batch_size=2)
    iterator = pipeline.skel_iterator(cfg.data, "train", process_index=0, process_count=1)
    batches = [next(iterator) for _ in range(2)]
    results = {}
    # One compilation per mesh, also with the sharded batch: two traces in all, or this raises.
    import chex

    skel.loss_fn = chex.assert_max_traces(skel.loss_fn, n=2)
    for name, devices in (("single", jax.devices()[:1]), ("sharded", jax.devices())):
        mesh = parallel.data_mesh(devices)
        graphdef, state = skel.build(cfg)
        state = parallel.replicate(state, mesh)
        step_fn, _ = skel.make_steps(graphdef, cfg, mesh)
        losses = []
        for batch in batches:
            inputs = skel.device_batch(batch, cfg, mesh)
            state, scalars = step_fn(state, inputs)
            losses.append(float(scalars["loss"]))
        results[name] = (losses, state, inputs["voxels"])
    (loss1, state1, _), (loss2, state2, voxels2) = results["single"], results["sharded"]
    compared = _compare_states(state2, state1, "['model']", cfg.optim.learning_rate, len(batches))
    np.testing.assert_allclose(loss2, loss1, rtol=1e-4, atol=1e-5)

    # The state checkpoints and restores into its replicated placement.
    with checkpoints.Checkpointer(workdir / "ckpt", keep=1) as ckpt:
        ckpt.save(2, state2)
        _, restored = ckpt.restore(checkpoints.abstract_state(state2))
    for a, b in zip(jax.tree.leaves(restored), jax.tree.leaves(state2), strict=True):
        assert a.sharding.is_equivalent_to(b.sharding, a.ndim)
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))

    refusal = ""
    try:
        odd = small_skel_config(root, batch_size=3, run=str(workdir / "odd"))
        skel.train_skeleton(odd, progress=False)
    except ValueError as err:
        refusal = str(err)
    return {
        "devices": len(jax.devices()),
        "losses": [loss1, loss2],
        "compared": compared,
        "batch_spec": str(voxels2.sharding.spec),
        "batch_shards": [list(s.data.shape) for s in voxels2.addressable_shards],
        "batch_devices": len({s.device for s in voxels2.addressable_shards}),
        "state_replicated": all(x.sharding.is_fully_replicated for x in jax.tree.leaves(state2)),
        "state_devices": len(jax.tree.leaves(state2)[0].sharding.device_set),
        "restored_replicated": all(
            x.sharding.is_fully_replicated for x in jax.tree.leaves(restored)
        ),
        "refusal": refusal,
        "odd_run_created": (workdir / "odd").exists(),
    }


def _script_dyn(workdir: Path) -> dict:
    import jax
    import jax.numpy as jnp
    from jax.sharding import PartitionSpec as P

    from nmjax import atomic
    from nmjax.train import dyn, dyn_inputs, parallel

    cfg = _dyn_cfg()
    rng = np.random.default_rng(0)
    # A smooth random trajectory table (30 frames, K=5); every start frame is valid.
    poses = np.cumsum(rng.normal(scale=0.05, size=(30, len(PARENTS), 4)), axis=0)
    poses[..., 3] = 0.8
    frames = cfg.data.frames
    poses, starts = poses.astype(np.float32), np.arange(30 - frames + 1, dtype=np.int32)
    table = dyn_inputs.CropTable(poses, starts, frames)
    draws = dyn.CropDraws(jax.random.key(3), table.num_starts, cfg.data.batch_size)
    results = {}
    seen = {}
    for name, devices in (("single", jax.devices()[:1]), ("sharded", jax.devices())):
        mesh = parallel.data_mesh(devices)
        graphdef, state = dyn.build(cfg, PARENTS, ORDER)
        state, key = parallel.replicate((state, jax.random.key(3)), mesh)
        step_fn = dyn.make_train_step(graphdef, cfg, mesh)
        losses = []
        for i in range(2):
            x = parallel.global_array(table.batch(draws.at(i)), mesh)
            state, metrics = step_fn(state, x, key, np.int32(i))
            losses.append(float(metrics["loss"]))
        results[name] = (losses, state)
        seen[name] = x = parallel.global_array(table.batch(draws.at(0)), mesh)  # the batch
    (loss1, state1), (loss2, state2) = results["single"], results["sharded"]
    compared = _compare_states(state2, state1, "['model']", cfg.optim.learning_rate, 2)
    np.testing.assert_allclose(loss2, loss1, rtol=1e-4, atol=1e-5)
    x = seen["sharded"]
    np.testing.assert_array_equal(np.asarray(x), np.asarray(seen["single"]))
    # A phase-1 run folder (contract C10) for the trainer, which must refuse batch 3 up front.
    skel_run = workdir / "skel-synth-arm-1"
    skel_run.mkdir()
    atomic.write_json(
        skel_run / "skeleton.json",
        {"parents": list(PARENTS), "root": 0, "order": list(ORDER), "depth": 3},
    )
    for split in ("train", "test"):
        atomic.save_npz(skel_run / f"keypoints_{split}.npz", seq=poses)
    refusal = ""
    odd = dataclasses.replace(_dyn_cfg(3), skel_run=str(skel_run), run=str(workdir / "odd"))
    try:
        dyn.train_dynamics(odd, progress=False)
    except ValueError as err:
        refusal = str(err)
    return {
        "devices": len(jax.devices()),
        "losses": [loss1, loss2],
        "compared": compared,
        "batch_spec": str(x.sharding.spec),
        "batch_is_data_sharded": x.sharding.spec == P("data"),
        "batch_shards": [list(s.data.shape) for s in x.addressable_shards],
        "batch_devices": len({s.device for s in x.addressable_shards}),
        "gathered_finite": bool(jnp.all(jnp.isfinite(x))),
        "refusal": refusal,
        "odd_run_created": (workdir / "odd").exists(),
    }


def _script_host(workdir: Path) -> dict:
    """One of two processes joined on localhost by the JAX_* environment variables, doing what a
    trainer does with the hosts (without its compiled step): the mesh over both, the run folder
    made by process 0, each host's slice of the seeded crop stream placed into the global batch,
    and a jitted reduction over that batch whose replicated result every host reads."""
    from nmjax.train import parallel

    assert parallel.initialize_distributed()  # from the environment, as under a scheduler
    import jax
    import jax.numpy as jnp

    from nmjax.data import pipeline

    cfg = small_skel_config(workdir / "data", batch_size=2)
    mesh = parallel.data_mesh()
    parallel.check_batch_size(cfg.data.batch_size, "data.batch_size", mesh)
    run = parallel.prepare_run_dir(workdir / "run", resume=False, config=cfg)
    data = dataclasses.replace(cfg.data, prefetch=0)
    local = next(pipeline.skel_iterator(data, seed=cfg.seed))["voxels"]  # this host's crops
    voxels = parallel.host_batch_to_global({"voxels": local}, mesh)["voxels"]
    sums = jax.jit(
        lambda v: jnp.sum(v, axis=(1, 2, 3, 4)), out_shardings=parallel.replicated(mesh)
    )(voxels)
    return {
        "process": jax.process_index(),
        "processes": jax.process_count(),
        "devices": len(jax.devices()),
        "primary": parallel.is_primary(),
        "local_crops": int(local.shape[0]),
        "global_shape": list(voxels.shape),
        "crop_sums": np.asarray(parallel.to_local(sums)).tolist(),
        "run_written": (run / "config.json").is_file(),
    }


def _xla_flags(devices: int) -> str:
    """The session's XLA flags (tests/conftest.py) with `devices` forced CPU devices."""
    return f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={devices}"


def _run_script(phase: str, workdir: Path) -> dict:
    env = {
        **os.environ,
        "XLA_FLAGS": _xla_flags(devices=2),
        "JAX_PLATFORMS": "cpu",
    }
    proc = subprocess.run(
        [sys.executable, __file__, phase, str(workdir)],
        env=env,
        capture_output=True,
        text=True,
    )  # no time limit: a loaded machine may take long to start a process
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


# --- tests ---------------------------------------------------------------------------------------


def test_phase1_sharded_step_equals_single_device_step(tmp_path):
    out = _run_script("skel", tmp_path)
    assert out["devices"] == 2
    assert out["compared"]["noise"] < 0.01 * out["compared"]["elements"]
    assert out["batch_spec"] == str(("data",)) or "data" in out["batch_spec"]
    assert out["batch_devices"] == 2 and [s[0] for s in out["batch_shards"]] == [1, 1]
    assert out["state_replicated"] and out["state_devices"] == 2
    assert out["restored_replicated"]
    assert all(np.isfinite(out["losses"][0]))
    assert "data.batch_size = 3" in out["refusal"] and "2 devices" in out["refusal"]
    assert "multiple of 2" in out["refusal"] and "--batch-size 4" in out["refusal"]
    assert not out["odd_run_created"]  # refused before the run folder or any compilation


def test_phase2_sharded_step_equals_single_device_step(tmp_path):
    out = _run_script("dyn", tmp_path)
    assert out["devices"] == 2
    assert out["compared"]["noise"] < 0.01 * out["compared"]["elements"]
    assert out["batch_is_data_sharded"], out["batch_spec"]
    assert out["batch_devices"] == 2 and [s[0] for s in out["batch_shards"]] == [2, 2]
    assert out["gathered_finite"]
    assert "data.batch_size = 3" in out["refusal"] and "2 devices" in out["refusal"]
    assert "--batch-size 4" in out["refusal"] and not out["odd_run_created"]


def test_one_device_refuses_nothing_and_mesh_has_the_data_axis():
    import jax

    from nmjax.train import parallel

    mesh = parallel.data_mesh()
    assert mesh.axis_names == ("data",) and mesh.devices.size == len(jax.devices())
    parallel.check_batch_size(3 * mesh.devices.size, "batch_size", mesh)
    with pytest.raises(ValueError, match="batch_size = 0"):
        parallel.check_batch_size(0, "batch_size", mesh)


def test_the_one_batch_check_names_the_field_and_the_nearest_batch_that_splits():
    from nmjax.config import check_batch_split

    check_batch_split(6, 3, "batch_size", "3 devices")
    with pytest.raises(ValueError) as refused:
        check_batch_split(5, 3, "batch_size", "3 devices", "--batch-size ", ", or use fewer")
    assert str(refused.value) == (
        "batch_size = 5 is the global batch, split evenly over 3 devices, so it must be a "
        "positive multiple of 3; set --batch-size 6 for example, or use fewer"
    )
    with pytest.raises(ValueError, match="set data.batch_size to 2 for example$"):
        check_batch_split(0, 2, "data.batch_size", "2 hosts")


def test_host_shards_of_the_pipeline_make_up_the_single_host_batch(tmp_path):
    from nmjax.data import pipeline, synthetic

    root = synthetic.generate(
        "synth-arm", tmp_path / "data", num_sequences=3, frames=8, points=500, progress=False
    )
    cfg = dataclasses.replace(small_skel_config(root, batch_size=4).data, prefetch=0)
    single = pipeline.skel_iterator(cfg, process_index=0, process_count=1)
    hosts = [pipeline.skel_iterator(cfg, process_index=p, process_count=2) for p in (0, 1)]
    for _ in range(2):
        whole = next(single)["voxels"]
        parts = [next(h)["voxels"] for h in hosts]
        assert [p.shape[0] for p in parts] == [2, 2]
        # Host p holds crops p, p + 2 of the global batch: interleaved, nothing lost or repeated.
        np.testing.assert_array_equal(parts[0], whole[0::2])
        np.testing.assert_array_equal(parts[1], whole[1::2])
    # The hosts refuse a batch with the devices' check (`config.check_batch_split`): the field,
    # the share and the nearest batch that splits.
    refusal = r"data.batch_size = 4 .* hosts \(3\).* multiple of 3; set data.batch_size to 3 for"
    with pytest.raises(ValueError, match=refusal):
        pipeline.skel_iterator(cfg, process_index=0, process_count=3)


def test_distributed_settings_from_flags_then_environment():
    from nmjax.train import parallel

    assert parallel.distributed_settings(env={}) is None
    env = {"JAX_COORDINATOR_ADDRESS": "h0:1234", "JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "1"}
    assert parallel.distributed_settings(env=env) == ("h0:1234", 2, 1)
    assert parallel.distributed_settings("h1:99", 4, 3, env=env) == ("h1:99", 4, 3)
    with pytest.raises(ValueError, match="--num-processes"):
        parallel.distributed_settings("h0:1234", env={})
    with pytest.raises(ValueError, match="--process-id must be in 0..1"):
        parallel.distributed_settings("h0:1234", 2, 2, env={})
    with pytest.raises(ValueError, match="--coordinator-address"):
        parallel.distributed_settings(None, 2, 0, env={})
    with pytest.raises(ValueError, match="JAX_PROCESS_ID must be an integer"):
        parallel.distributed_settings(env={**env, "JAX_PROCESS_ID": "one"})


def test_trainer_commands_accept_and_check_the_distributed_flags(capsys):
    from nmjax.cli import main as nmjax_main
    from nmjax.cli.train import train_config, train_parser

    args = train_parser("skel").parse_args(
        ["--coordinator-address", "h0:1", "--num-processes", "2"]
    )
    assert args.coordinator_address == "h0:1" and args.num_processes == 2
    assert args.process_id is None
    # A coordinator without a process id is refused before JAX is initialised.
    argv = ["--coordinator-address", "h0:1", "--num-processes", "2"]
    assert nmjax_main(["train-skel", *argv]) == 2
    assert "--process-id" in capsys.readouterr().err
    assert nmjax_main(["train-dyn", "--preset", "tiny", "--coordinator-address", "h0:1"]) == 2
    assert "--num-processes" in capsys.readouterr().err
    args = train_parser("dyn").parse_args(["--batch-size", "6", "--process-id", "0"])
    assert train_config(args, "dyn").data.batch_size == 6


def _free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("localhost", 0))
        return sock.getsockname()[1]


def _two_processes(argv, env) -> list[tuple[str, str]]:
    """Runs processes 0 and 1 together (`argv(i)`, `env(i)`), waits for both and asserts each
    exited 0; returns their (stdout, stderr)."""
    procs = [
        subprocess.Popen(
            argv(i), env=env(i), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        for i in (0, 1)
    ]
    outputs = [proc.communicate(timeout=600) for proc in procs]
    for proc, (_, err) in zip(procs, outputs, strict=True):
        assert proc.returncode == 0, err[-3000:]
    return outputs


def test_two_processes_join_and_feed_one_global_batch(tmp_path):
    """Two processes joined with jax.distributed on localhost (one CPU device each, set by the
    environment variables): each feeds its half of every global batch, and the batch they make
    together is the single host's (the fast half of the slow two-host training test below)."""
    from nmjax.data import pipeline, synthetic

    synthetic.generate(
        "synth-arm", tmp_path / "data", num_sequences=3, frames=8, points=500, progress=False
    )
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "XLA_FLAGS": _xla_flags(devices=1)}
    env |= {"JAX_COORDINATOR_ADDRESS": f"localhost:{_free_port()}", "JAX_NUM_PROCESSES": "2"}
    outputs = _two_processes(
        lambda i: [sys.executable, __file__, "host", str(tmp_path)],
        lambda i: {**env, "JAX_PROCESS_ID": str(i)},
    )
    hosts = [json.loads(out.strip().splitlines()[-1]) for out, _ in outputs]
    assert [(h["process"], h["processes"], h["devices"]) for h in hosts] == [(0, 2, 2), (1, 2, 2)]
    assert [h["primary"] for h in hosts] == [True, False]
    assert [h["local_crops"] for h in hosts] == [1, 1]
    assert all(h["global_shape"][0] == 2 and h["run_written"] for h in hosts)
    cfg = small_skel_config(tmp_path / "data", batch_size=2)
    data = dataclasses.replace(cfg.data, prefetch=0)
    whole = next(pipeline.skel_iterator(data, seed=cfg.seed, process_index=0, process_count=1))
    expected = whole["voxels"].sum(axis=(1, 2, 3, 4))
    for host in hosts:  # every host reads the whole batch's result: crop 0 from host 0, 1 from 1
        np.testing.assert_allclose(host["crop_sums"], expected, rtol=1e-6)


@pytest.mark.slow
def test_two_hosts_train_like_one_host_with_two_devices(tmp_path):
    """Two processes with one CPU device each (jax.distributed on localhost, each feeding its
    half of every batch) log exactly the losses of one process with two devices."""
    from nmjax.data import synthetic

    root = synthetic.generate(
        "synth-arm", tmp_path / "data", num_sequences=2, frames=6, points=500, progress=False
    )
    argv = [sys.executable, "-m", "nmjax.cli", "train-skel", "--data", "synth-arm"]
    argv += ["--preset", "tiny", "--root", str(root), "--steps", "3", "--no-progress"]
    for change in ("data.grid=8", "model.grid=8", "model.channels=4", "data.frames=3"):
        argv += ["--set", change]
    argv += ["--set", "model.hourglass_channels=4,4,4", "--set", "val_every=3"]
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    one = subprocess.run(
        [*argv, "--run", str(tmp_path / "one")],
        env={**env, "XLA_FLAGS": _xla_flags(devices=2)},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert one.returncode == 0, one.stderr[-3000:]
    hosts = ["--coordinator-address", f"localhost:{_free_port()}", "--num-processes", "2"]
    _two_processes(
        lambda i: [*argv, "--run", str(tmp_path / "two"), *hosts, "--process-id", str(i)],
        lambda i: {**env, "XLA_FLAGS": _xla_flags(devices=1)},
    )
    from nmjax.train import metric_log

    expected, got = (
        metric_log.read_metrics(tmp_path / "one"),
        metric_log.read_metrics(tmp_path / "two"),
    )
    assert [r["step"] for r in got] == [r["step"] for r in expected]
    for a, b in zip(got, expected, strict=True):
        assert a.keys() == b.keys()
        for key in a:
            if key != "train/steps_per_s":
                assert a[key] == pytest.approx(b[key], rel=1e-5, abs=1e-6), key
    assert (tmp_path / "two" / "skeleton.json").is_file()
    assert (tmp_path / "two" / "keypoints_test.npz").is_file()


if __name__ == "__main__":
    phase, workdir = sys.argv[1], Path(sys.argv[2])
    result = {"skel": _script_skel, "dyn": _script_dyn, "host": _script_host}[phase](workdir)
    print(json.dumps(result))
