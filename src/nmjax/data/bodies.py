"""The articulated bodies of the built-in synthetic datasets (`synth-*`), as data.

A body is a tree of joints; each joint owns a few degrees of freedom (with limits and a group whose
members share a random signal) and a few rigid links (trimesh capsules, cylinders and boxes) given
in its local frame. `nmjax.data.synthetic` moves, poses and samples them.

The tables are the data file bodies.json shipped with the package (its "about" entries say the
units and what each body is), read once into `BODIES` (`read_bodies`): `synth-hand` (palm and
five three-segment fingers, 21 joints; curl and spread), `synth-arm` (a Panda-like arm with 7
revolute joints and a two-finger gripper), `synth-human` (19 joints, limb motion with a
gait-like coupling plus root translation) and `synth-quadruped` (25 joints, trotting legs, neck,
wagging tail, root translation). Units are arbitrary; every body is about one unit across, with
z up.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from importlib import resources
from typing import Any

import numpy as np
import trimesh

DEG = np.pi / 180.0  # the file's angles are degrees
BODIES_FILE = "bodies.json"  # in the package nmjax.data

# --------------------------------------------------------------------------------------------
# Body description


@dataclass(frozen=True)
class Dof:
    """One degree of freedom of a joint.

    Attributes:
      axis: unit axis in the joint's frame (after its fixed rest rotation).
      lower, upper: joint limits, radians for "rotate", body units for "slide".
      kind: "rotate" (about `axis`) or "slide" (along `axis`).
      group: degrees of freedom sharing a group name share one random signal per sequence.
      coupling: weight of the group signal in [-1, 1] (negative: mirrored); the own signal gets
        1 - |coupling|.
    """

    axis: tuple[float, float, float]
    lower: float
    upper: float
    kind: str = "rotate"
    group: str | None = None
    coupling: float = 0.0


@dataclass(frozen=True)
class Link:
    """A rigid piece of surface in its joint's frame.

    "capsule" and "cylinder" run from `a` to `b` with `radius`; "box" has centre `a` and extents
    `b`.
    """

    shape: str
    a: tuple[float, float, float]
    b: tuple[float, float, float]
    radius: float = 0.0

    def mesh(self) -> trimesh.Trimesh:
        """The link's triangle mesh in its joint's frame."""
        a, b = np.asarray(self.a, float), np.asarray(self.b, float)
        if self.shape == "box":
            return trimesh.creation.box(
                extents=b, transform=trimesh.transformations.translation_matrix(a)
            )
        if self.shape == "cylinder":
            return trimesh.creation.cylinder(
                radius=self.radius, segment=np.stack([a, b]), sections=16
            )
        if self.shape == "capsule":
            length = float(np.linalg.norm(b - a))
            transform = np.eye(4)
            if length > 0:
                transform[:3, :3] = trimesh.geometry.align_vectors(
                    [0.0, 0.0, 1.0], (b - a) / length
                )[:3, :3]
            transform[:3, 3] = (a + b) / 2
            return trimesh.creation.capsule(
                height=length, radius=self.radius, count=[12, 12], transform=transform
            )
        raise ValueError(f"unknown link shape {self.shape!r}; use capsule, cylinder or box")


@dataclass(frozen=True)
class Joint:
    """A joint: a frame placed on its parent, moved by its degrees of freedom.

    Attributes:
      name: joint name, unique in the body.
      parent: parent joint name; None for the root.
      offset: position in the parent's frame (for the root: its rest position in the world).
      radius: thickness of the body at the joint: the joint lies within `radius` of the surface.
      dofs: degrees of freedom, applied in order after the rest rotation.
      links: rigid surface pieces moving with this joint.
      rest: fixed rotation from the parent's frame, Euler angles (x, y, z) in radians applied as
        Rz @ Ry @ Rx.
    """

    name: str
    parent: str | None
    offset: tuple[float, float, float]
    radius: float
    dofs: tuple[Dof, ...] = ()
    links: tuple[Link, ...] = ()
    rest: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Body:
    """An articulated body and the statistics of its random motions.

    Attributes:
      name: dataset name ("synth-...").
      joints: the joints, every parent listed before its children; joints[0] is the root.
      period: range of the sinusoid periods of the joint signals, in frames.
      speed: largest forward speed of the root along its local x axis, units per frame.
      wander: amplitude of the smooth random root translation per axis, units.
      frames: default range (inclusive) of sequence lengths.
      num_sequences: default number of sequences of a set.
    """

    name: str
    joints: tuple[Joint, ...]
    period: tuple[float, float] = (30.0, 90.0)
    speed: float = 0.0
    wander: tuple[float, float, float] = (0.0, 0.0, 0.0)
    frames: tuple[int, int] = (50, 80)
    num_sequences: int = 30

    @property
    def joint_names(self) -> list[str]:
        return [j.name for j in self.joints]

    @property
    def parents(self) -> list[int]:
        """Parent index of every joint; the root is its own parent."""
        index = {j.name: i for i, j in enumerate(self.joints)}
        return [i if j.parent is None else index[j.parent] for i, j in enumerate(self.joints)]

    @property
    def dofs(self) -> list[tuple[int, Dof]]:
        """(joint index, dof) for every degree of freedom, in joint order: the columns of angles."""
        return [(i, d) for i, j in enumerate(self.joints) for d in j.dofs]

    @property
    def limits(self) -> np.ndarray:
        """(D, 2) lower and upper limit of every degree of freedom."""
        return np.array([[d.lower, d.upper] for _, d in self.dofs], dtype=np.float64).reshape(-1, 2)


def _check_body(body: Body) -> Body:
    names = body.joint_names
    if len(set(names)) != len(names):
        raise ValueError(f"{body.name}: joint names must be unique")
    if body.joints[0].parent is not None or any(j.parent is None for j in body.joints[1:]):
        raise ValueError(f"{body.name}: exactly the first joint must be the root (parent None)")
    for i, j in enumerate(body.joints[1:], start=1):
        if j.parent not in names[:i]:
            raise ValueError(f"{body.name}: parent {j.parent!r} of {j.name!r} must come before it")
    for _, d in body.dofs:
        if not d.lower < d.upper or d.kind not in ("rotate", "slide"):
            raise ValueError(f"{body.name}: bad degree of freedom {d}")
    return body


# --------------------------------------------------------------------------------------------
# The tables (bodies.json)


def _vector(value: Any) -> tuple[float, float, float]:
    x, y, z = value
    return (float(x), float(y), float(z))


def _dof(entry: dict[str, Any]) -> Dof:
    kind = entry.get("kind", "rotate")
    lower, upper = entry["limits"]
    if kind == "rotate":  # degrees in the file
        lower, upper = lower * DEG, upper * DEG
    return Dof(
        _vector(entry["axis"]),
        float(lower),
        float(upper),
        kind=kind,
        group=entry.get("group"),
        coupling=float(entry.get("coupling", 0.0)),
    )


def _joint(entry: dict[str, Any]) -> Joint:
    return Joint(
        entry["name"],
        entry["parent"],
        _vector(entry["offset"]),
        float(entry["radius"]),
        dofs=tuple(_dof(d) for d in entry.get("dofs", ())),
        links=tuple(
            Link(
                link["shape"], _vector(link["a"]), _vector(link["b"]), float(link.get("radius", 0))
            )
            for link in entry.get("links", ())
        ),
        rest=_vector(np.multiply(entry.get("rest", (0, 0, 0)), DEG)),
    )


def _body(name: str, entry: dict[str, Any]) -> Body:
    low, high = entry["frames"]
    return Body(
        name,
        tuple(_joint(j) for j in entry["joints"]),
        period=(float(entry["period"][0]), float(entry["period"][1])),
        speed=float(entry["speed"]),
        wander=_vector(entry["wander"]),
        frames=(int(low), int(high)),
        num_sequences=int(entry["num_sequences"]),
    )


def read_bodies(text: str | None = None) -> dict[str, Body]:
    """The bodies of bodies.json (or of `text`, the same form), checked.

    Raises:
      ValueError: an entry that is missing a field or breaks the tree's rules, naming the body.
    """
    if text is None:
        text = resources.files("nmjax.data").joinpath(BODIES_FILE).read_text(encoding="utf-8")
    bodies = {}
    for name, entry in json.loads(text)["bodies"].items():
        try:
            bodies[name] = _check_body(_body(name, entry))
        except (KeyError, TypeError) as err:
            raise ValueError(
                f"{BODIES_FILE}: body {name!r} has a malformed entry ({err!r})"
            ) from err
    return bodies


BODIES: dict[str, Body] = read_bodies()


def get_body(name: str) -> Body:
    """The body of synthetic dataset `name`; unknown names list the valid ones."""
    if name not in BODIES:
        raise ValueError(
            f"unknown synthetic dataset {name!r}; valid names: {', '.join(sorted(BODIES))}"
        )
    return BODIES[name]
