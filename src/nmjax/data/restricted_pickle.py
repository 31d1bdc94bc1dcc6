"""The one restricted unpickler of nmjax: pickles read admitting only the globals a caller lists.

Unpickling an arbitrary file can run code: a pickle names globals (classes, functions) that the
reader imports and calls. Every pickle nmjax reads (SMPL / MANO model files and AIST++ motions in
`nmjax.data.body_models`, the release's PyTorch checkpoint and opt.pickle in
`nmjax.release.checkpoint`) goes through `RestrictedUnpickler`, which resolves a global only from
the caller's allow-list (or a hook for a family of names) and refuses every other one before
anything of it is imported or built (`RefusedGlobal`).
"""

from __future__ import annotations

import io
import pickle
from collections.abc import Callable, Mapping
from typing import Any, BinaryIO


class RefusedGlobal(pickle.UnpicklingError):
    """A pickle names a global outside the allow-list; nothing of it was imported or built.

    `str()` is "module.name"; the attributes `module` and `name` hold the two parts.
    """

    def __init__(self, module: str, name: str):
        super().__init__(f"{module}.{name}")
        self.module, self.name = module, name


class RestrictedUnpickler(pickle.Unpickler):
    """A `pickle.Unpickler` that resolves only the globals it is given.

    Args:
      file: an open binary file or the pickle's bytes.
      allowed: {(module, name): object}: each global the pickle may name, and what it resolves
        to (the real class or function, or an inert stand-in that rebuilds only data).
      other: optional hook (module, name) -> object or None, consulted for a global not in
        `allowed`, for a family of names no table can list (one stand-in per chumpy class);
        None refuses the global.
      persistent_load: optional hook pid -> object for the pickle's persistent ids (PyTorch's
        storages); without it a persistent id is refused.
      encoding: as `pickle.Unpickler`'s; "latin1" reads a Python 2 pickle's byte strings.

    Raises (from `load`):
      RefusedGlobal: a global outside `allowed` that `other` does not resolve.
      pickle.UnpicklingError: a persistent id without a `persistent_load` hook, or a damaged
        pickle; whatever the hooks raise passes through.
    """

    def __init__(
        self,
        file: BinaryIO | bytes,
        allowed: Mapping[tuple[str, str], Any],
        *,
        other: Callable[[str, str], Any] | None = None,
        persistent_load: Callable[[Any], Any] | None = None,
        encoding: str = "ASCII",
    ):
        super().__init__(io.BytesIO(file) if isinstance(file, bytes) else file, encoding=encoding)
        self._allowed = allowed
        self._other = other
        self._persistent = persistent_load

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in self._allowed:
            return self._allowed[module, name]
        found = None if self._other is None else self._other(module, name)
        if found is None:
            raise RefusedGlobal(module, name)
        return found

    def persistent_load(self, pid: Any) -> Any:
        if self._persistent is None:
            raise pickle.UnpicklingError(f"refused a persistent id {pid!r:.80} (none admitted)")
        return self._persistent(pid)
