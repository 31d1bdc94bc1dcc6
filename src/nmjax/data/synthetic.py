"""Built-in synthetic articulated datasets: procedural bodies with ground-truth joints (C4).

A fresh clone can train without downloading anything: `generate("synth-hand", root)` writes a set
in the layout every loader reads (`nmjax.data.datasets`),

    <root>/<split>/vertices/<seq>.npy   (T, N, 3) float32  surface points, N = 20,000 by default
    <root>/<split>/joints/<seq>.npy     (T, J, 3) float32  ground-truth joint positions
    <root>/<split>/angles/<seq>.npy     (T, D) float32     the joint-angle trajectory that posed it
    <root>/split.json                   {"train": [...], "test": [...]}  (9:1 by sequence count)
    <root>/meta.json                    joint names, parents (root is its own parent), ... and
                                        "complete": true, written last

Four bodies live in `BODIES`: `synth-hand` (palm and five three-segment fingers, 21 joints; curl
and spread), `synth-arm` (a Panda-like arm with 7 revolute joints and a two-finger gripper),
`synth-human` (19 joints, limb motion with a gait-like coupling plus root translation) and
`synth-quadruped` (25 joints, trotting legs, neck, wagging tail, root translation). A body is a
tree of joints; each joint owns a few rigid links (trimesh capsules, cylinders and boxes) given in
its local frame. A sequence is made by

  1. drawing a smooth joint-angle trajectory within the joint limits (`sample_motion`): every
     degree of freedom follows a normalised sum of three random sinusoids, optionally mixed with a
     signal shared by its group (a finger's curl, the hand's spread, a gait phase), mapped into a
     random sub-range of its limits and clipped to them;
  2. posing the joints by forward kinematics (`pose`, NumPy, vectorised over frames);
  3. sampling surface points area-uniformly (`sample_surface`): the links are rigid, so triangles
     are drawn on the rest-pose link meshes with probability proportional to their area, and the
     samples are carried into every frame by their joint's rotation and position.

Everything is deterministic for a seed: the set's generator `np.random.default_rng(seed)` draws the
sequence lengths and spawns one child generator per sequence, so the same seed gives the same
bytes. Units are arbitrary; every body is about one unit across, with z up.
"""

from __future__ import annotations

import functools
import json
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from tqdm import tqdm

from nmjax.data.prepare import write_index, write_sequence

DEG = np.pi / 180.0
SPLITS = ("train", "test")
_SEQ_NAME = re.compile(r"seq_\d+")


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
# The four bodies


def _hand() -> Body:
    """Palm facing -z, fingers along +x, thumb on the +y side; flexion bends towards -z."""
    y_axis, z_axis = (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
    joints = [
        Joint(
            "wrist",
            None,
            (0.0, 0.0, 0.0),
            0.05,
            dofs=(
                Dof(z_axis, -20 * DEG, 20 * DEG),  # radial / ulnar deviation
                Dof(y_axis, -35 * DEG, 35 * DEG),  # flexion / extension
                Dof((1.0, 0.0, 0.0), -30 * DEG, 30 * DEG),  # pronation / supination
            ),
            links=(Link("box", (0.175, 0.0, 0.0), (0.35, 0.34, 0.1)),),
        )
    ]
    # name, knuckle y, segment lengths, radius, coupling to the hand's spread signal
    fingers = (
        ("index", 0.12, (0.19, 0.12, 0.09), 0.034, 0.8),
        ("middle", 0.04, (0.21, 0.13, 0.10), 0.035, 0.0),
        ("ring", -0.04, (0.20, 0.125, 0.095), 0.033, -0.6),
        ("pinky", -0.12, (0.16, 0.10, 0.08), 0.030, -0.8),
    )
    for name, y, (l1, l2, l3), r, spread in fingers:
        curl = f"{name}_curl"
        joints += [
            Joint(
                f"{name}1",
                "wrist",
                (0.35, y, 0.0),
                r,
                dofs=(
                    Dof(
                        z_axis,
                        -15 * DEG,
                        15 * DEG,
                        group="spread" if spread else None,
                        coupling=spread,
                    ),
                    Dof(y_axis, -15 * DEG, 85 * DEG, group=curl, coupling=0.75),
                ),
                links=(Link("capsule", (0.0, 0.0, 0.0), (l1, 0.0, 0.0), r),),
            ),
            Joint(
                f"{name}2",
                f"{name}1",
                (l1, 0.0, 0.0),
                r,
                dofs=(Dof(y_axis, 0.0, 100 * DEG, group=curl, coupling=0.75),),
                links=(Link("capsule", (0.0, 0.0, 0.0), (l2, 0.0, 0.0), 0.95 * r),),
            ),
            Joint(
                f"{name}3",
                f"{name}2",
                (l2, 0.0, 0.0),
                0.95 * r,
                dofs=(Dof(y_axis, 0.0, 80 * DEG, group=curl, coupling=0.85),),
                links=(Link("capsule", (0.0, 0.0, 0.0), (l3, 0.0, 0.0), 0.9 * r),),
            ),
            Joint(f"{name}_tip", f"{name}3", (l3, 0.0, 0.0), 0.9 * r),
        ]
    # The thumb leaves the palm diagonally, rolled towards the palm side.
    joints[1:1] = [
        Joint(
            "thumb1",
            "wrist",
            (0.07, 0.15, -0.02),
            0.04,
            dofs=(
                Dof(z_axis, -15 * DEG, 25 * DEG, group="spread", coupling=0.5),
                Dof(y_axis, -10 * DEG, 50 * DEG, group="thumb_curl", coupling=0.7),
            ),
            links=(Link("capsule", (0.0, 0.0, 0.0), (0.15, 0.0, 0.0), 0.04),),
            rest=(-35 * DEG, 0.0, 50 * DEG),
        ),
        Joint(
            "thumb2",
            "thumb1",
            (0.15, 0.0, 0.0),
            0.04,
            dofs=(Dof(y_axis, 0.0, 55 * DEG, group="thumb_curl", coupling=0.7),),
            links=(Link("capsule", (0.0, 0.0, 0.0), (0.11, 0.0, 0.0), 0.037),),
        ),
        Joint(
            "thumb3",
            "thumb2",
            (0.11, 0.0, 0.0),
            0.037,
            dofs=(Dof(y_axis, 0.0, 80 * DEG, group="thumb_curl", coupling=0.8),),
            links=(Link("capsule", (0.0, 0.0, 0.0), (0.09, 0.0, 0.0), 0.034),),
        ),
        Joint("thumb_tip", "thumb3", (0.09, 0.0, 0.0), 0.034),
    ]
    return Body("synth-hand", tuple(joints), period=(40.0, 120.0))


def _arm() -> Body:
    """A Panda-like arm standing on the origin: alternating z / y axes, a flange and a gripper."""
    y_axis, z_axis = (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
    o = (0.0, 0.0, 0.0)

    def seg(end: tuple[float, float, float], r: float) -> tuple[Link, ...]:
        return (Link("capsule", o, end, r),)

    joints = [
        Joint(
            "base",
            None,
            o,
            0.08,
            links=(
                Link("cylinder", o, (0.0, 0.0, 0.06), 0.12),
                Link("capsule", o, (0.0, 0.0, 0.25), 0.075),
            ),
        ),
        Joint(
            "joint1",
            "base",
            (0.0, 0.0, 0.25),
            0.075,
            (Dof(z_axis, -90 * DEG, 90 * DEG),),
            seg((0.0, 0.0, 0.1), 0.07),
        ),
        Joint(
            "joint2",
            "joint1",
            (0.0, 0.0, 0.1),
            0.07,
            (Dof(y_axis, -50 * DEG, 50 * DEG),),
            seg((0.0, 0.0, 0.28), 0.065),
        ),
        Joint(
            "joint3",
            "joint2",
            (0.0, 0.0, 0.28),
            0.065,
            (Dof(z_axis, -70 * DEG, 70 * DEG),),
            seg((0.07, 0.0, 0.1), 0.06),
        ),
        Joint(
            "joint4",
            "joint3",
            (0.07, 0.0, 0.1),
            0.06,
            (Dof(y_axis, 20 * DEG, 120 * DEG),),
            seg((-0.07, 0.0, 0.1), 0.06),
        ),
        Joint(
            "joint5",
            "joint4",
            (-0.07, 0.0, 0.1),
            0.06,
            (Dof(z_axis, -80 * DEG, 80 * DEG),),
            seg((0.0, 0.0, 0.24), 0.055),
        ),
        Joint(
            "joint6",
            "joint5",
            (0.0, 0.0, 0.24),
            0.055,
            (Dof(y_axis, -20 * DEG, 110 * DEG),),
            seg((0.08, 0.0, 0.0), 0.05),
        ),
        Joint(
            "joint7",
            "joint6",
            (0.08, 0.0, 0.0),
            0.05,
            (Dof((0.0, 0.0, -1.0), -90 * DEG, 90 * DEG),),
            seg((0.0, 0.0, -0.08), 0.045),
        ),
        Joint(
            "hand",
            "joint7",
            (0.0, 0.0, -0.1),
            0.04,
            links=(Link("box", (0.0, 0.0, -0.03), (0.06, 0.2, 0.06)),),
        ),
    ]
    for side, sign in (("left", 1.0), ("right", -1.0)):
        finger = Link("box", (0.0, 0.0, -0.035), (0.035, 0.03, 0.07))
        joints += [
            Joint(
                f"finger_{side}",
                "hand",
                (0.0, sign * 0.025, -0.06),
                0.03,
                (Dof((0.0, sign, 0.0), 0.0, 0.045, kind="slide", group="grip", coupling=1.0),),
                (finger,),
            ),
            Joint(f"fingertip_{side}", f"finger_{side}", (0.0, 0.0, -0.07), 0.03),
        ]
    return Body("synth-arm", tuple(joints), period=(50.0, 120.0))


def _human() -> Body:
    """A standing figure about 1.1 units tall: x forward, y to its left, z up."""
    x_axis, y_axis, z_axis = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
    forward = (0.0, -1.0, 0.0)  # rotating a downward limb about -y swings it forwards
    o = (0.0, 0.0, 0.0)
    joints = [
        Joint(
            "pelvis",
            None,
            (0.0, 0.0, 0.5),
            0.06,
            (
                Dof(z_axis, -60 * DEG, 60 * DEG),
                Dof(y_axis, -10 * DEG, 10 * DEG),
                Dof(x_axis, -8 * DEG, 8 * DEG),
            ),
            (Link("box", o, (0.12, 0.22, 0.1)),),
        ),
        Joint(
            "spine",
            "pelvis",
            (0.0, 0.0, 0.08),
            0.06,
            (
                Dof(y_axis, -15 * DEG, 30 * DEG),
                Dof(x_axis, -15 * DEG, 15 * DEG),
                Dof(z_axis, -25 * DEG, 25 * DEG),
            ),
            (Link("capsule", o, (0.0, 0.0, 0.14), 0.06),),
        ),
        Joint(
            "chest",
            "spine",
            (0.0, 0.0, 0.14),
            0.07,
            (Dof(y_axis, -10 * DEG, 20 * DEG), Dof(z_axis, -20 * DEG, 20 * DEG)),
            (Link("box", (0.0, 0.0, 0.08), (0.13, 0.28, 0.16)),),
        ),
        Joint(
            "neck",
            "chest",
            (0.0, 0.0, 0.17),
            0.04,
            (Dof(y_axis, -20 * DEG, 35 * DEG), Dof(z_axis, -40 * DEG, 40 * DEG)),
            (Link("capsule", o, (0.0, 0.0, 0.06), 0.035),),
        ),
        Joint(
            "head",
            "neck",
            (0.0, 0.0, 0.07),
            0.06,
            links=(Link("capsule", (0.0, 0.0, 0.04), (0.0, 0.0, 0.09), 0.06),),
        ),
    ]
    for side, s in (("l", 1.0), ("r", -1.0)):
        joints += [
            Joint(
                f"{side}_shoulder",
                "chest",
                (0.0, s * 0.17, 0.13),
                0.04,
                (
                    Dof(forward, -60 * DEG, 80 * DEG, group="gait", coupling=-0.6 * s),
                    Dof((s, 0.0, 0.0), 0.0, 90 * DEG),
                    Dof(z_axis, -30 * DEG, 30 * DEG),
                ),
                (Link("capsule", o, (0.0, 0.0, -0.17), 0.035),),
            ),
            Joint(
                f"{side}_elbow",
                f"{side}_shoulder",
                (0.0, 0.0, -0.17),
                0.035,
                (Dof(forward, 0.0, 120 * DEG),),
                (Link("capsule", o, (0.0, 0.0, -0.15), 0.03),),
            ),
            Joint(
                f"{side}_wrist",
                f"{side}_elbow",
                (0.0, 0.0, -0.15),
                0.03,
                links=(Link("capsule", o, (0.0, 0.0, -0.06), 0.03),),
            ),
        ]
    for side, s in (("l", 1.0), ("r", -1.0)):
        joints += [
            Joint(
                f"{side}_hip",
                "pelvis",
                (0.0, s * 0.08, -0.05),
                0.05,
                (
                    Dof(forward, -30 * DEG, 50 * DEG, group="gait", coupling=0.8 * s),
                    Dof((s, 0.0, 0.0), -10 * DEG, 25 * DEG),
                    Dof(z_axis, -20 * DEG, 20 * DEG),
                ),
                (Link("capsule", o, (0.0, 0.0, -0.22), 0.05),),
            ),
            Joint(
                f"{side}_knee",
                f"{side}_hip",
                (0.0, 0.0, -0.22),
                0.045,
                (Dof(y_axis, 0.0, 100 * DEG),),
                (Link("capsule", o, (0.0, 0.0, -0.2), 0.04),),
            ),
            Joint(
                f"{side}_ankle",
                f"{side}_knee",
                (0.0, 0.0, -0.2),
                0.04,
                (Dof(y_axis, -25 * DEG, 25 * DEG),),
                (Link("box", (0.035, 0.0, -0.025), (0.13, 0.06, 0.05)),),
            ),
            Joint(f"{side}_toe", f"{side}_ankle", (0.1, 0.0, -0.04), 0.03),
        ]
    return Body(
        "synth-human", tuple(joints), period=(30.0, 80.0), speed=0.008, wander=(0.05, 0.05, 0.02)
    )


def _quadruped() -> Body:
    """A dog-like body about 1.2 units long: x forward, y to its left, z up."""
    x_axis, y_axis, z_axis = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
    forward, backward = (0.0, -1.0, 0.0), (0.0, 1.0, 0.0)
    o = (0.0, 0.0, 0.0)
    joints = [
        Joint(
            "torso",
            None,
            (0.0, 0.0, 0.45),
            0.11,
            (
                Dof(z_axis, -45 * DEG, 45 * DEG),
                Dof(y_axis, -8 * DEG, 8 * DEG),
                Dof(x_axis, -6 * DEG, 6 * DEG),
            ),
            (Link("capsule", (-0.25, 0.0, 0.0), (0.25, 0.0, 0.0), 0.11),),
        ),
        Joint(
            "withers",
            "torso",
            (0.25, 0.0, 0.0),
            0.11,
            (Dof(y_axis, -10 * DEG, 10 * DEG), Dof(z_axis, -15 * DEG, 15 * DEG)),
            (Link("capsule", o, (0.08, 0.0, 0.0), 0.11),),
        ),
        Joint(
            "hips",
            "torso",
            (-0.25, 0.0, 0.0),
            0.1,
            (Dof(y_axis, -10 * DEG, 10 * DEG), Dof(z_axis, -12 * DEG, 12 * DEG)),
            (Link("capsule", o, (-0.06, 0.0, 0.0), 0.1),),
        ),
        Joint(
            "neck",
            "withers",
            (0.1, 0.0, 0.05),
            0.06,
            (Dof(y_axis, -25 * DEG, 25 * DEG), Dof(z_axis, -35 * DEG, 35 * DEG)),
            (Link("capsule", o, (0.2, 0.0, 0.0), 0.06),),
            rest=(0.0, -50 * DEG, 0.0),
        ),
        Joint(
            "head",
            "neck",
            (0.2, 0.0, 0.0),
            0.075,
            (Dof(y_axis, -20 * DEG, 20 * DEG),),
            (
                Link("capsule", o, (0.06, 0.0, 0.0), 0.075),
                Link("capsule", (0.06, 0.0, 0.0), (0.16, 0.0, 0.0), 0.045),
            ),
            rest=(0.0, 60 * DEG, 0.0),
        ),
        Joint("nose", "head", (0.16, 0.0, 0.0), 0.045),
        Joint(
            "tail1",
            "hips",
            (-0.08, 0.0, 0.04),
            0.035,
            (
                Dof(z_axis, -40 * DEG, 40 * DEG, group="wag", coupling=0.8),
                Dof(y_axis, -20 * DEG, 20 * DEG),
            ),
            (Link("capsule", o, (-0.15, 0.0, 0.0), 0.03),),
            rest=(0.0, 30 * DEG, 0.0),
        ),
        Joint(
            "tail2",
            "tail1",
            (-0.15, 0.0, 0.0),
            0.03,
            (
                Dof(z_axis, -40 * DEG, 40 * DEG, group="wag", coupling=0.8),
                Dof(y_axis, -20 * DEG, 20 * DEG),
            ),
            (Link("capsule", o, (-0.13, 0.0, 0.0), 0.025),),
        ),
        Joint("tail_tip", "tail2", (-0.13, 0.0, 0.0), 0.025),
    ]
    # Trot: diagonal legs swing together (front-left with hind-right).
    for leg, parent, x, s, trot in (
        ("fl", "withers", 0.02, 1.0, 0.8),
        ("fr", "withers", 0.02, -1.0, -0.8),
        ("hl", "hips", 0.0, 1.0, -0.8),
        ("hr", "hips", 0.0, -1.0, 0.8),
    ):
        front = leg[0] == "f"
        names = ("shoulder", "elbow", "wrist") if front else ("hip", "knee", "hock")
        upper, middle, lower = (f"{leg}_{n}" for n in names)
        joints += [
            Joint(
                upper,
                parent,
                (x, s * 0.08, -0.06),
                0.05,
                (
                    Dof(forward, -35 * DEG, 35 * DEG, group="trot", coupling=trot),
                    Dof((s, 0.0, 0.0), -10 * DEG, 10 * DEG),
                ),
                (Link("capsule", o, (0.0, 0.0, -0.17), 0.045),),
            ),
            Joint(
                middle,
                upper,
                (0.0, 0.0, -0.17),
                0.04,
                (Dof(backward if front else forward, 0.0, 60 * DEG if front else 50 * DEG),),
                (Link("capsule", o, (0.0, 0.0, -0.15), 0.035),),
            ),
            Joint(
                lower,
                middle,
                (0.0, 0.0, -0.15),
                0.035,
                (Dof(forward if front else backward, -10 * DEG if front else 0.0, 30 * DEG),),
                (Link("capsule", o, (0.04, 0.0, -0.06), 0.03),),
            ),
            Joint(f"{leg}_paw", lower, (0.04, 0.0, -0.06), 0.03),
        ]
    return Body(
        "synth-quadruped",
        tuple(joints),
        period=(30.0, 80.0),
        speed=0.005,
        wander=(0.04, 0.04, 0.015),
    )


BODIES: dict[str, Body] = {
    b.name: _check_body(b) for b in (_hand(), _arm(), _human(), _quadruped())
}


def get_body(name: str) -> Body:
    """The body of synthetic dataset `name`; unknown names list the valid ones."""
    if name not in BODIES:
        raise ValueError(
            f"unknown synthetic dataset {name!r}; valid names: {', '.join(sorted(BODIES))}"
        )
    return BODIES[name]


# --------------------------------------------------------------------------------------------
# Motion, kinematics and surface sampling


def _smooth_signals(
    rng: np.random.Generator, count: int, frames: int, period: tuple[float, float]
) -> np.ndarray:
    """(count, frames) smooth signals spanning [-1, 1]: sums of three random sinusoids.

    Each sum is stretched to run from exactly -1 to 1 over the sequence, so that every degree of
    freedom sweeps its whole sampled sub-range (a visible motion) however short the sequence.
    """
    t = np.arange(frames, dtype=np.float64)
    weights = rng.uniform(0.2, 1.0, size=(count, 3))
    freqs = 1.0 / rng.uniform(*period, size=(count, 3))
    phases = rng.uniform(0.0, 2 * np.pi, size=(count, 3))
    waves = np.sin(2 * np.pi * freqs[..., None] * t + phases[..., None])  # (count, 3, frames)
    sums = np.einsum("ck,ckt->ct", weights, waves)
    low, high = sums.min(-1, keepdims=True), sums.max(-1, keepdims=True)
    return 2.0 * (sums - low) / np.maximum(high - low, 1e-12) - 1.0


def sample_motion(
    body: Body, frames: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Draws one smooth random motion of `body` within its joint limits.

    Every degree of freedom mixes its own signal with its group's, c = w g + (1 - |w|) s in [-1, 1],
    and maps it into a random sub-range of its limits: angle = mid + half (c0 + a c) with amplitude
    a ~ U(0.5, 1) and centre c0 ~ U(-(1 - a), 1 - a), clipped to the limits. The root drifts
    forward along its (horizontal) local x axis at a random speed up to `body.speed` and wanders
    smoothly by up to `body.wander` per axis.

    Args:
      body: the body.
      frames: number of frames T.
      rng: random generator.

    Returns:
      angles (T, D) in the column order of `body.dofs`, root translation (T, 3).
    """
    dofs = body.dofs
    groups = sorted({d.group for _, d in dofs if d.group is not None})
    own = _smooth_signals(rng, len(dofs), frames, body.period)  # (D, T)
    shared = dict(zip(groups, _smooth_signals(rng, len(groups), frames, body.period), strict=True))
    coupling = np.array([d.coupling if d.group else 0.0 for _, d in dofs])[:, None]
    group_signal = np.stack([shared[d.group] if d.group else np.zeros(frames) for _, d in dofs])
    mixed = coupling * group_signal + (1.0 - np.abs(coupling)) * own
    amplitude = rng.uniform(0.5, 1.0, size=(len(dofs), 1))
    centre = rng.uniform(-1.0, 1.0, size=(len(dofs), 1)) * (1.0 - amplitude)
    limits = body.limits
    mid, half = limits.mean(-1, keepdims=True), (limits[:, 1:] - limits[:, :1]) / 2
    angles = np.clip(mid + half * (centre + amplitude * mixed), limits[:, :1], limits[:, 1:]).T

    wander = _smooth_signals(rng, 3, frames, body.period).T * np.asarray(body.wander)  # (T, 3)
    speed = rng.uniform(0.0, body.speed)
    root_rotation = _local_rotations(body.joints[0], angles[:, : len(body.joints[0].dofs)])
    heading = root_rotation[:, :, 0] * np.array([1.0, 1.0, 0.0])  # local x, made horizontal
    heading /= np.maximum(np.linalg.norm(heading, axis=-1, keepdims=True), 1e-9)
    drift = np.cumsum(speed * heading, axis=0) - speed * heading[:1]
    return angles, wander - wander[:1] + drift


def _axis_angle(axis: Sequence[float], angle: np.ndarray) -> np.ndarray:
    """(T, 3, 3) rotations about a fixed unit `axis` by `angle` (T,), Rodrigues' formula."""
    k = np.asarray(axis, dtype=np.float64)
    k = k / np.linalg.norm(k)
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * cross + (1.0 - c) * (cross @ cross)


def _euler(rest: Sequence[float]) -> np.ndarray:
    """(3, 3) rotation Rz @ Ry @ Rx of Euler angles (x, y, z)."""
    rx, ry, rz = (_axis_angle(a, np.array([r]))[0] for a, r in zip(np.eye(3), rest, strict=True))
    return rz @ ry @ rx


def _local_rotations(joint: Joint, angles: np.ndarray) -> np.ndarray:
    """(T, 3, 3) rest rotation times the joint's rotations, for its angle columns (T, D_j)."""
    rotation = np.broadcast_to(_euler(joint.rest), (angles.shape[0], 3, 3))
    for column, dof in enumerate(joint.dofs):
        if dof.kind == "rotate":
            rotation = rotation @ _axis_angle(dof.axis, angles[:, column])
    return rotation


def pose(
    body: Body, angles: np.ndarray, root_translation: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Forward kinematics: joint positions and frames for every frame.

    p_j = p_parent + R_parent (offset_j + Rest_j sum_slide theta axis),
    R_j = R_parent Rest_j prod_rotate R(axis, theta); the root's parent frame is the world moved by
    `root_translation`. The loop runs over joints; every operation is vectorised over frames.

    Args:
      body: the body.
      angles: (T, D) in the column order of `body.dofs`.
      root_translation: (T, 3).

    Returns:
      positions (T, J, 3) and world rotations (T, J, 3, 3) of the joints.
    """
    angles = np.asarray(angles, dtype=np.float64)
    frames = angles.shape[0]
    if angles.shape != (frames, len(body.dofs)):
        raise ValueError(
            f"angles must have shape (T, {len(body.dofs)}) for {body.name}, got {angles.shape}"
        )
    positions = np.zeros((frames, len(body.joints), 3))
    rotations = np.zeros((frames, len(body.joints), 3, 3))
    parents, start = body.parents, 0
    for j, joint in enumerate(body.joints):
        cols = angles[:, start : start + len(joint.dofs)]
        start += len(joint.dofs)
        slide_axes = np.array(
            [d.axis if d.kind == "slide" else (0.0, 0.0, 0.0) for d in joint.dofs]
        ).reshape(-1, 3)
        local_position = np.asarray(joint.offset) + cols @ slide_axes @ _euler(joint.rest).T
        if joint.parent is None:
            parent_rotation, parent_position = np.eye(3), np.asarray(root_translation, np.float64)
        else:
            parent_rotation, parent_position = rotations[:, parents[j]], positions[:, parents[j]]
        positions[:, j] = parent_position + np.einsum(
            "...ij,...j->...i", parent_rotation, local_position
        )
        rotations[:, j] = parent_rotation @ _local_rotations(joint, cols)
    return positions, rotations


@functools.cache
def body_triangles(body: Body) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of every link in its joint's frame: (F, 3, 3) corners and (F,) joint index."""
    triangles, owner = [], []
    for j, joint in enumerate(body.joints):
        for link in joint.links:
            mesh = link.mesh()
            triangles.append(np.asarray(mesh.triangles, dtype=np.float64))
            owner.append(np.full(len(mesh.faces), j))
    return np.concatenate(triangles), np.concatenate(owner)


def rest_mesh(body: Body) -> trimesh.Trimesh:
    """The body's surface (all links, not merged) with every angle zero, for tests and pictures."""
    positions, rotations = pose(body, np.zeros((1, len(body.dofs))), np.zeros((1, 3)))
    triangles, owner = body_triangles(body)
    world = np.einsum("fij,fcj->fci", rotations[0, owner], triangles) + positions[0, owner, None]
    return trimesh.Trimesh(**trimesh.triangles.to_kwargs(world))


def sample_surface(
    body: Body,
    positions: np.ndarray,
    rotations: np.ndarray,
    points: int,
    rng: np.random.Generator,
    chunk: int = 16,
) -> np.ndarray:
    """Area-uniform surface samples of the posed body, drawn independently for every frame.

    Rigid links keep their area, so a triangle is picked with probability proportional to its
    rest-pose area, a point uniformly inside it (u = sqrt(r1): (1-u) A + u (1-r2) B + u r2 C), and
    the point is carried by its joint's transform. Frames go in chunks to bound memory.

    Args:
      body: the body.
      positions: (T, J, 3) joint positions from `pose`.
      rotations: (T, J, 3, 3) joint rotations from `pose`.
      points: N, samples per frame.
      rng: random generator.
      chunk: frames transformed at once.

    Returns:
      (T, N, 3) float32 points.
    """
    triangles, owner = body_triangles(body)
    areas = np.linalg.norm(
        np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]), axis=-1
    )
    cumulative = np.cumsum(areas)
    out = np.empty((positions.shape[0], points, 3), dtype=np.float32)
    for start in range(0, positions.shape[0], chunk):
        stop = min(start + chunk, positions.shape[0])
        shape = (stop - start, points)
        face = np.minimum(
            np.searchsorted(cumulative, rng.random(shape) * cumulative[-1], side="right"),
            len(areas) - 1,
        )
        u, r2 = np.sqrt(rng.random(shape))[..., None], rng.random(shape)[..., None]
        tri = triangles[face]  # (t, N, 3, 3)
        local = (1 - u) * tri[..., 0, :] + u * (1 - r2) * tri[..., 1, :] + u * r2 * tri[..., 2, :]
        frame = np.arange(start, stop)[:, None]
        joint = owner[face]
        world = np.einsum("tnij,tnj->tni", rotations[frame, joint], local) + positions[frame, joint]
        out[start:stop] = world
    return out


@dataclass(frozen=True)
class SyntheticSequence:
    """One generated sequence: surface points (T, N, 3) float32, joints (T, J, 3) float32,
    angles (T, D) float32 and root translation (T, 3) float32."""

    vertices: np.ndarray
    joints: np.ndarray
    angles: np.ndarray
    root_translation: np.ndarray


def simulate(
    name: str, frames: int, *, points: int = 20000, rng: np.random.Generator | int = 0
) -> SyntheticSequence:
    """Draws a motion of body `name`, poses it and samples its surface (steps 1-3 of the module)."""
    body = get_body(name)
    if frames < 1 or points < 1:
        raise ValueError(
            f"frames and points must be positive, got frames={frames}, points={points}"
        )
    rng = np.random.default_rng(rng) if isinstance(rng, int) else rng
    angles, root = sample_motion(body, frames, rng)
    positions, rotations = pose(body, angles, root)
    vertices = sample_surface(body, positions, rotations, points, rng)
    return SyntheticSequence(
        vertices, positions.astype(np.float32), angles.astype(np.float32), root.astype(np.float32)
    )


# --------------------------------------------------------------------------------------------
# Writing a set


def is_complete(root: str | Path) -> bool:
    """True when `root` holds a finished set: meta.json exists and says "complete": true."""
    try:
        meta = json.loads((Path(root) / "meta.json").read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return False
    return isinstance(meta, dict) and meta.get("complete") is True


def split_names(num_sequences: int) -> dict[str, list[str]]:
    """Sequence names per split: the last max(1, round(n / 10)) sequences are the test split."""
    if num_sequences < 2:
        raise ValueError(
            f"num_sequences must be at least 2 (one train, one test), got {num_sequences}"
        )
    names = [f"seq_{i:03d}" for i in range(num_sequences)]
    num_test = max(1, round(num_sequences / 10))
    return {"train": names[:-num_test], "test": names[-num_test:]}


def generate(
    name: str,
    root: str | Path,
    *,
    num_sequences: int | None = None,
    frames: int | None = None,
    points: int = 20000,
    seed: int = 0,
    progress: bool = True,
) -> Path:
    """Writes synthetic dataset `name` into `root` in the nmjax layout (see the module docstring).

    meta.json is removed first and written last with "complete": true, so an interrupted run never
    looks finished (`is_complete`); every file is written atomically. Sequence files left from an
    earlier, larger set in `root` are deleted. Same arguments, same bytes.

    Args:
      name: one of `BODIES` ("synth-hand", "synth-arm", "synth-human", "synth-quadruped").
      root: the dataset folder, e.g. data/synth-hand.
      num_sequences: number of sequences (default: the body's, 30); 9:1 train/test, >= 1 test.
      frames: frames per sequence (default: random per sequence in the body's range, 50-80).
      points: surface points per frame.
      seed: seed of the whole set.
      progress: show a tqdm bar over sequences.

    Returns:
      `root` as a Path.
    """
    body = get_body(name)
    num_sequences = body.num_sequences if num_sequences is None else int(num_sequences)
    splits = split_names(num_sequences)
    if frames is not None and frames < 2:
        raise ValueError(f"frames must be at least 2 (a sequence needs motion), got {frames}")
    if points < 1:
        raise ValueError(f"points must be positive, got {points}")
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    (root / "meta.json").unlink(missing_ok=True)

    rng = np.random.default_rng(seed)
    if frames is None:
        lengths = rng.integers(body.frames[0], body.frames[1] + 1, size=num_sequences)
    else:
        lengths = np.full(num_sequences, frames)
    children = rng.spawn(num_sequences)
    jobs = [(split, seq) for split in SPLITS for seq in splits[split]]
    for index, (split, seq) in enumerate(
        tqdm(jobs, desc=f"generating {name}", unit="seq", disable=not progress)
    ):
        sequence = simulate(name, int(lengths[index]), points=points, rng=children[index])
        write_sequence(
            root,
            split,
            seq,
            vertices=sequence.vertices,
            joints=sequence.joints,
            angles=sequence.angles,
        )
    for split in SPLITS:
        for kind in ("vertices", "joints", "angles"):
            for path in (root / split / kind).glob("*.npy"):
                if _SEQ_NAME.fullmatch(path.stem) and path.stem not in splits[split]:
                    path.unlink()
    write_index(
        root,
        splits,
        {
            "name": name,
            "joint_names": body.joint_names,
            "parents": body.parents,
            "joint_radius": [j.radius for j in body.joints],
            "dofs": [
                {
                    "joint": body.joints[j].name,
                    "kind": d.kind,
                    "axis": list(d.axis),
                    "limits": [d.lower, d.upper],
                }
                for j, d in body.dofs
            ],
            "sample_rate": 1,
            "seed": seed,
            "num_sequences": num_sequences,
            "frames": {seq: int(lengths[i]) for i, (_, seq) in enumerate(jobs)},
            "points": points,
            "generator": "nmjax.data.synthetic",
            "complete": True,
        },
    )
    return root
