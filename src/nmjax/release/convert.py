"""The conversion: the release's tensors written into freshly built nmjax networks.

`fill` applies a name/layout map (`nmjax.release.layout`) and refuses a parameter left unfilled
or shapes that disagree; `check_all_used` refuses a tensor left over; `build_networks` does both
for the detector and the dynamics model.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from nmjax.release.layout import Entry, detector_entries, dynamics_entries


def _names(items: Iterable[Any], limit: int = 6) -> str:
    items = [".".join(map(str, i)) if isinstance(i, tuple) else str(i) for i in items]
    more = f" and {len(items) - limit} more" if len(items) > limit else ""
    return ", ".join(items[:limit]) + more


def fill(model: Any, entries: list[Entry], tensors: Mapping[str, np.ndarray], what: str) -> set:
    """Writes the converted release tensors into every variable of `model` (nnx.state: the
    parameters and the frozen buffers); returns the names of the tensors used.

    Raises:
      ValueError: one line naming the tensors the map needs but the checkpoint lacks, the
        variables no entry fills, or every tensor whose shape is not the one the variable needs
        (both shapes named).
    """
    import jax.numpy as jnp
    from flax import nnx

    state = nnx.state(model)
    variables = dict(nnx.to_flat_state(state))
    absent = sorted({s for e in entries for s in e.sources if s not in tensors})
    unmapped = [p for p in variables if p not in {e.target for e in entries}]
    if absent or unmapped:
        parts = [f"the checkpoint lacks {_names(absent)}"] if absent else []
        parts += [f"no tensor fills {what}'s {_names(unmapped)}"] if unmapped else []
        raise ValueError(f"{'; '.join(parts)}: it is not the network of these options")
    mismatched, values = [], {}
    for entry in entries:
        if entry.target not in variables:
            raise ValueError(f"{what} has no variable {_names([entry.target])} (name map)")
        shape = tuple(variables[entry.target].shape)
        wanted = entry.layout.release_shapes(shape)
        arrays = [tensors[s] for s in entry.sources]
        bad = [
            f"{s} has shape {a.shape}, {what}'s {_names([entry.target])} {shape} needs {w}"
            for s, a, w in zip(entry.sources, arrays, wanted, strict=True)
            if a.shape != w
        ]
        if bad:
            mismatched += bad
            continue
        values[entry.target] = np.asarray(entry.layout.convert(*arrays), np.float32)
    if mismatched:
        more = f" (and {len(mismatched) - 3} more)" if len(mismatched) > 3 else ""
        raise ValueError(
            f"shapes disagree: {'; '.join(mismatched[:3])}{more}: the options do not describe "
            "this checkpoint; give the opt.pickle saved with it"
        )
    for path, value in values.items():
        variables[path].set_value(jnp.asarray(value))
    nnx.update(model, state)
    return {s for e in entries for s in e.sources}


def check_all_used(tensors: Mapping[str, np.ndarray], used: set) -> None:
    """Raises ValueError naming every tensor of the checkpoint that no entry consumed."""
    left = [name for name in tensors if name not in used]
    if left:
        raise ValueError(
            f"the checkpoint has {len(left)} tensor(s) nmjax's networks have no place for: "
            f"{_names(left)}; it is not the released Neural Marionette network"
        )


def build_networks(tensors: Mapping[str, np.ndarray], skel_cfg: Any, dyn_cfg: Any) -> tuple:
    """(detector, dynamics, skeleton) of the release: both networks built from the
    configurations and filled from `tensors`; the skeleton (Algorithm 1 on the imported
    affinity) is the dynamics model's tree.

    Raises:
      ValueError: as `fill` and `check_all_used`.
    """
    from flax import nnx

    from nmjax.models.detector import KeypointDetector
    from nmjax.models.dynamics import Dynamics
    from nmjax.skeleton import DEFAULT_NEIGHBORS, extract_skeleton

    detector = KeypointDetector(skel_cfg.model, rngs=nnx.Rngs(skel_cfg.seed))
    used = fill(detector, detector_entries(detector), tensors, "the detector")
    skeleton = extract_skeleton(np.asarray(detector.affinity()), DEFAULT_NEIGHBORS)
    # Built abstractly (no initialisation to compute): `fill` gives every variable its value.
    dynamics = nnx.eval_shape(
        lambda: Dynamics(dyn_cfg.model, skeleton.parents, skeleton.order, rngs=nnx.Rngs(0))
    )
    used |= fill(dynamics, dynamics_entries(dynamics), tensors, "the dynamics model")
    check_all_used(tensors, used)
    return detector, dynamics, skeleton
