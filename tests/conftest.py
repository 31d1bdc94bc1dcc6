"""Fixtures every test module shares."""

from __future__ import annotations

import gc

import pytest


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
