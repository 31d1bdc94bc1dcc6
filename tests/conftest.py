"""Fixtures every test module shares."""

from __future__ import annotations

import gc
import os

import pytest

# `make test` runs two pytest workers; on a GPU, JAX's default of taking 75% of the device's
# memory at start-up in each process would leave the second worker without any. Read when the
# backend starts, so set before any test computes.
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drops JAX's compiled programs after each test module.

    On CPU each compiled program keeps about five memory mappings of machine code until it is
    released, and the suite compiles thousands of programs in one process: kept, they pass the
    kernel's limit on mappings per process (vm.max_map_count, 65,530 by default), and XLA's next
    compilation dies with a segmentation fault. A module's tests still share what they compile.
    """
    yield
    import jax

    jax.clear_caches()
    gc.collect()
