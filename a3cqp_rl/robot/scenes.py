"""MJCF scene objects for the Panda experiments (paper 000, section VI): the peg-in-hole block and the polishing plate.

Each function returns MJCF bodies for the worldbody (PandaSim(scene=...), a3cqp_rl.robot.mjcf.compose_mjcf); every
geom is finite (boxes), so PandaSim can replicate the scene for N arms. Collision classes as in panda.xml: scene geoms
are contype 1 / conaffinity 2, the arm and its tool contype 2 / conaffinity 1.

Why the hole is a polygon of boxes: MuJoCo has no hollow primitive, and a mesh bore is replaced by its convex hull in
collisions. A ring of `segments` boxes whose inner faces are tangent to the bore circle makes a regular polygon with
apothem = bore radius, i.e. the radial clearance to a centred cylinder peg is exactly (bore − peg) / 2 at the faces
(more at the polygon's corners: apothem / cos(π / segments), +0.5 % for 32 segments). The boxes are made wider than
a polygon side so that neighbours overlap outside the bore (no gaps on the top face for the peg's rim to catch in);
the overlap lies behind the neighbouring inner faces, so the bore stays the exact polygon.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["HoleGeometry", "hole_block_xml", "plate_xml"]

_SCENE_GEOM = 'contype="1" conaffinity="2" priority="1"'  # priority: the scene's friction and solref rule its contacts
_VISUAL = 'contype="0" conaffinity="0"'


@dataclass(frozen=True)
class HoleGeometry:
    """A block with a vertical cylindrical bore (paper 000: peg Ø 20.0 mm, hole Ø 20.5 mm in a bench vise)."""

    center: tuple[float, float] = (0.45, 0.0)
    """Bore axis position (x, y) [m], world frame of the arm's copy."""
    top: float = 0.30
    """Height of the block's top face (the hole's rim) [m]."""
    bore_diameter: float = 0.0205
    """Hole diameter [m] (polygon inscribed-circle diameter)."""
    depth: float = 0.04
    """Bore depth below the rim [m] (a floor closes it)."""
    segments: int = 32
    """Boxes around the bore (polygon sides)."""
    ring_radius: float = 0.05
    """Outer apothem of the ring of boxes [m]."""
    half_size: float = 0.07
    """Half side of the square block [m]."""
    friction: float = 0.3
    """Sliding friction coefficient of the block (MuJoCo takes the max of the two geoms')."""
    solref: tuple[float, float] = (0.005, 1.0)
    """MuJoCo contact solref (time constant [s], damping ratio) of the block: stiff (2 timesteps)."""
    solimp: tuple[float, float, float] = (0.95, 0.99, 0.0005)
    """MuJoCo contact solimp (d0, d_width, width [m]) of the block."""

    @property
    def bore_radius(self) -> float:
        """Bore radius (polygon apothem) [m]."""
        return 0.5 * self.bore_diameter

    def __post_init__(self) -> None:
        if self.segments < 8:
            raise ValueError(f"segments must be >= 8 for a round bore, got {self.segments}")
        if not 0 < self.bore_radius < self.ring_radius < self.half_size:
            raise ValueError(f"need 0 < bore radius < ring_radius < half_size, got {self.bore_radius}, "
                             f"{self.ring_radius}, {self.half_size}")
        if self.depth <= 0:
            raise ValueError(f"depth must be > 0, got {self.depth}")


def hole_block_xml(g: HoleGeometry = HoleGeometry(), name: str = "hole_block") -> str:
    """MJCF body of the block with its bore: a ring of boxes around the bore, a square frame, a floor and a stand."""
    r_in, r_out, n = g.bore_radius, g.ring_radius, g.segments
    thick = r_out - r_in
    # half-width: covers the polygon side at the outer apothem, so neighbouring boxes overlap all the way
    half_w = r_out * math.tan(math.pi / n) * 1.05
    half_h = 0.5 * g.depth
    contact = (f'{_SCENE_GEOM} friction="{g.friction} 0.005 0.0001" solref="{g.solref[0]} {g.solref[1]}" '
               f'solimp="{g.solimp[0]} {g.solimp[1]} {g.solimp[2]}"')
    parts = [f'<body name="{name}" pos="{g.center[0]} {g.center[1]} {g.top}">']
    for k in range(n):
        a = 2.0 * math.pi * k / n
        c = r_in + 0.5 * thick
        parts.append(f'<geom name="{name}_seg{k}" type="box" size="{0.5 * thick} {half_w} {half_h}" '
                     f'pos="{c * math.cos(a):.9f} {c * math.sin(a):.9f} {-half_h}" quat="{math.cos(a / 2):.12f} 0 0 {math.sin(a / 2):.12f}" '
                     f'{contact} rgba="0.55 0.57 0.6 1"/>')
    # square frame around the ring: its opening (half side `inner`) lies inside the ring's outer apothem at the
    # corners, so frame and ring leave no gap on the top face
    inner = 0.98 * r_out / math.sqrt(2.0)
    hs, bar = g.half_size, 0.5 * (g.half_size - inner)
    for k, (x, y, sx, sy) in enumerate(((inner + bar, 0.0, bar, hs), (-inner - bar, 0.0, bar, hs),
                                         (0.0, inner + bar, inner, bar), (0.0, -inner - bar, inner, bar))):
        parts.append(f'<geom name="{name}_frame{k}" type="box" size="{sx} {sy} {half_h}" pos="{x} {y} {-half_h}" '
                     f'{contact} rgba="0.55 0.57 0.6 1"/>')
    parts.append(f'<geom name="{name}_floor" type="box" size="{hs} {hs} 0.005" pos="0 0 {-g.depth - 0.005}" '
                 f'{contact} rgba="0.45 0.47 0.5 1"/>')
    stand = g.top - g.depth - 0.01  # a visual stand (the vise) down to the floor of the scene
    if stand > 0:
        parts.append(f'<geom name="{name}_stand" type="box" size="{0.8 * hs} {0.8 * hs} {0.5 * stand}" '
                     f'pos="0 0 {-g.depth - 0.01 - 0.5 * stand}" {_VISUAL} rgba="0.3 0.3 0.35 1"/>')
    parts.append(f'<site name="{name}_rim" pos="0 0 0" size="0.003" rgba="0 1 0 1"/>')
    parts.append("</body>")
    return "\n".join(parts)


def plate_xml(center: tuple[float, float] = (0.45, 0.0), top: float = 0.25, half_size: tuple[float, float] = (0.2, 0.25),
              thickness: float = 0.02, friction: float = 0.3, name: str = "plate", tool_geom: str | None = None,
              friction_solref: tuple[float, float] = (0.3, 1.0)) -> str:
    """MJCF body of a wooden plate (polishing) whose top face is at `top` [m], on a visual stand.

    With `tool_geom` (the polishing disc's geom, e.g. "disc") the plate-tool contact is an explicit pair under
    MuJoCo's elliptic friction cone whose frictional rows get their own `friction_solref` (time constant [s],
    damping ratio); the `<option>` and `<contact>` elements come after the body (compose_mjcf moves them to the
    model's top level). Why: with one solref for normal and friction (pyramidal cone), a contact sliding under
    Coulomb friction is pushed apart at about μ |v_t| (MuJoCo's convex contact model), and the disc hopped on the
    plate at the polishing circle's speed (docs/panda.md, "Why the plate's friction has its own solref")."""
    solref = "0.004 1"  # the plate's normal: stiff (4 ms)
    contact = f'friction="{friction} 0.005 0.0001" solref="{solref}"'
    parts = [f'<body name="{name}" pos="{center[0]} {center[1]} {top - 0.5 * thickness}">',
             f'<geom name="{name}" type="box" size="{half_size[0]} {half_size[1]} {0.5 * thickness}" {_SCENE_GEOM} '
             f'{contact} rgba="0.76 0.6 0.42 1"/>']
    stand = top - thickness
    if stand > 0:
        parts.append(f'<geom name="{name}_stand" type="box" size="{0.6 * half_size[0]} {0.6 * half_size[1]} '
                     f'{0.5 * stand}" pos="0 0 {-0.5 * thickness - 0.5 * stand}" {_VISUAL} rgba="0.3 0.3 0.35 1"/>')
    parts.append("</body>")
    if tool_geom is not None:
        if not (len(friction_solref) == 2 and all(v > 0 for v in friction_solref)):
            raise ValueError(f"friction_solref needs (time constant [s], damping ratio), both > 0, "
                             f"got {friction_solref}")
        # the pair repeats the plate's contact (condim 3: μ on both tangent axes) and adds the friction rows' solref
        parts.append('<option cone="elliptic"/>')
        parts.append(f'<contact><pair geom1="{name}" geom2="{tool_geom}" condim="3" '
                     f'friction="{friction} {friction} 0.005 0.0001 0.0001" solref="{solref}" '
                     f'solreffriction="{friction_solref[0]} {friction_solref[1]}"/></contact>')
    return "\n".join(parts)
