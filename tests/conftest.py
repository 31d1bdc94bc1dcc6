"""Fixtures every test module shares."""

from __future__ import annotations

import gc
import os
import shutil
import tempfile

import pytest

# `make test` runs two pytest workers; on a GPU, JAX's default of taking 75% of the device's
# memory at start-up in each process would leave the second worker without any. Read when the
# backend starts, so set before any test computes.
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

# The tests' programs are tiny, so compiling them is nearly all of the suite's time, and most of
# that is LLVM optimising machine code that then runs a few steps: with LLVM's optimisations off
# the tiny train step compiles in about half the time. XLA's CPU fusion emitters (the MLIR ones)
# take about half of what is left: with the older emitters the tests' G=8 phase-1 train step
# compiles in 4.3 s against 8.4 s, and 6 steps of it give the same loss to 8 digits. The results
# are the same functions (XLA enables no fast-math at any level); benchmarks and training runs
# keep XLA's defaults.
_FAST_COMPILE = (
    "--xla_backend_optimization_level=0",
    "--xla_llvm_disable_expensive_passes=true",
    "--xla_cpu_use_fusion_emitters=false",
)
_flags = os.environ.get("XLA_FLAGS", "")
if "xla_backend_optimization_level" not in _flags:
    os.environ["XLA_FLAGS"] = " ".join([_flags, *_FAST_COMPILE]).strip()

# One compilation cache on disk for the whole test session: the pytest workers and the commands
# the tests start in subprocesses inherit it, so a program that several tests compile (the tiny
# presets' training and evaluation steps above all) is compiled once and loaded from disk after.
# Cached programs are keyed by their HLO, JAX's version and the backend's options, so a hit is
# the same program. The main process (the xdist controller, or pytest itself without workers)
# makes the folder before any worker starts and removes it at the end; a cache the user set is
# used as it is and left alone.
_SESSION_CACHE = "NMJAX_TEST_COMPILATION_CACHE"
if "JAX_COMPILATION_CACHE_DIR" not in os.environ and "PYTEST_XDIST_WORKER" not in os.environ:
    os.environ["JAX_COMPILATION_CACHE_DIR"] = os.environ[_SESSION_CACHE] = tempfile.mkdtemp(
        prefix="nmjax-test-jax-cache-"
    )
if _SESSION_CACHE in os.environ:
    # Cache every program, however small or quick to compile (JAX's defaults skip those).
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "-1")


def pytest_unconfigure(config):
    if "PYTEST_XDIST_WORKER" not in os.environ and _SESSION_CACHE in os.environ:
        shutil.rmtree(os.environ.pop(_SESSION_CACHE), ignore_errors=True)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drops JAX's compiled programs after each test module.

    On CPU each compiled program keeps about five memory mappings of machine code until it is
    released, and the suite compiles thousands of programs in one process: kept, they pass the
    kernel's limit on mappings per process (vm.max_map_count, 65,530 by default), and XLA's next
    compilation dies with a segmentation fault. A module's tests still share what they compile;
    the session's compilation cache on disk gives them back to later modules cheaply.
    """
    yield
    import jax

    jax.clear_caches()
    gc.collect()


@pytest.fixture(scope="module")
def data_root(tmp_path_factory):
    """The trainer tests' synth-arm set (`tiny_configs.small_arm_data`), one per test module."""
    from tiny_configs import small_arm_data

    return small_arm_data(tmp_path_factory.mktemp("data") / "synth-arm")


@pytest.fixture(scope="module")
def fake_run(tmp_path_factory):
    """A fake phase-1 run (`tiny_runs.make_fake_run`) named as `nmjax train-skel` names one."""
    from tiny_runs import make_fake_run

    return make_fake_run(tmp_path_factory.mktemp("phase1") / "skel-synth-arm-20260101-000000")
