"""The articulated bodies of the built-in synthetic datasets (`synth-*`), as data.

A body is a tree of joints; each joint owns a few degrees of freedom (with limits and a group whose
members share a random signal) and a few rigid links (trimesh capsules, cylinders and boxes) given
in its local frame. `nmjax.data.synthetic` moves, poses and samples them.

Four bodies live in `BODIES`: `synth-hand` (palm and five three-segment fingers, 21 joints; curl
and spread), `synth-arm` (a Panda-like arm with 7 revolute joints and a two-finger gripper),
`synth-human` (19 joints, limb motion with a gait-like coupling plus root translation) and
`synth-quadruped` (25 joints, trotting legs, neck, wagging tail, root translation). Units are
arbitrary; every body is about one unit across, with z up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

DEG = np.pi / 180.0

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
