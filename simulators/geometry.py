"""Triangle meshes of simple parametric primitives (boxes, prisms, cylinders, dishes).

Every primitive carries its own vertex normals: smooth for curved surfaces (cylinder
sides, dishes, spheres) and per face for flat ones, so the rasteriser can interpolate
them. Surfaces are two-sided (the shader turns a normal that faces away from the
camera), so open shells such as a dish or a solar panel need no thickness.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

Vec = Sequence[float]


@dataclass(frozen=True)
class Mesh:
    vertices: np.ndarray  # (N, 3) float64
    normals: np.ndarray  # (N, 3) float64, unit length
    triangles: np.ndarray  # (M, 3) int32

    def transformed(self, rot: np.ndarray | None = None, shift: Vec = (0.0, 0.0, 0.0)) -> Mesh:
        r = np.eye(3) if rot is None else np.asarray(rot, dtype=np.float64)
        moved = self.vertices @ r.T + np.asarray(shift, dtype=np.float64)
        return Mesh(moved, self.normals @ r.T, self.triangles)

    def moved(self, shift: Vec) -> Mesh:
        return self.transformed(None, shift)

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)


def concat(meshes: Iterable[Mesh]) -> Mesh:
    meshes = list(meshes)
    if not meshes:
        return Mesh(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int32))
    offs = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    return Mesh(
        np.concatenate([m.vertices for m in meshes]),
        np.concatenate([m.normals for m in meshes]),
        np.concatenate([m.triangles + o for m, o in zip(meshes, offs, strict=True)]).astype(np.int32),
    )


# -- rotations (degrees, right-handed) ------------------------------------------------
def rot_x(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def align_z(direction: Vec) -> np.ndarray:
    """A rotation taking +z onto ``direction``."""
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(z, d)
    c = float(z @ d)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def _unit(a: np.ndarray) -> np.ndarray:
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


# -- primitives (built about the origin, axis +z) ----------------------------------------
def box(size: Vec, center: Vec = (0.0, 0.0, 0.0)) -> Mesh:
    """Axis-aligned box with flat faces."""
    h = np.asarray(size, dtype=np.float64) / 2.0
    verts, norms, tris = [], [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            n = np.zeros(3)
            n[axis] = sign
            u, v = [a for a in range(3) if a != axis]
            quad = []
            for du, dv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = np.zeros(3)
                p[axis] = sign * h[axis]
                p[u], p[v] = du * h[u], dv * h[v]
                quad.append(p)
            base = len(verts)
            verts += quad
            norms += [n] * 4
            tris += [(base, base + 1, base + 2), (base, base + 2, base + 3)]
    return Mesh(np.array(verts), np.array(norms), np.array(tris, dtype=np.int32)).moved(center)


def frustum(
    r0: float, r1: float, z0: float, z1: float, sides: int = 32, *, smooth: bool = True,
    caps: bool = True,
) -> Mesh:
    """A (truncated) cone or cylinder about +z from ``z0`` (radius r0) to ``z1`` (radius r1).

    ``smooth=False`` gives a faceted prism (e.g. Voyager's decagonal bus).
    """
    ang = np.linspace(0.0, 2 * np.pi, sides + 1)
    slope = (r0 - r1) / (z1 - z0) if z1 != z0 else 0.0
    verts, norms, tris = [], [], []
    for i in range(sides):
        a0, a1 = ang[i], ang[i + 1]
        if smooth:
            na = [a0, a1]
        else:
            mid = 0.5 * (a0 + a1)
            na = [mid, mid]
        n0 = _unit(np.array([np.cos(na[0]), np.sin(na[0]), slope]))
        n1 = _unit(np.array([np.cos(na[1]), np.sin(na[1]), slope]))
        base = len(verts)
        verts += [
            (r0 * np.cos(a0), r0 * np.sin(a0), z0), (r0 * np.cos(a1), r0 * np.sin(a1), z0),
            (r1 * np.cos(a1), r1 * np.sin(a1), z1), (r1 * np.cos(a0), r1 * np.sin(a0), z1),
        ]
        norms += [n0, n1, n1, n0]
        tris += [(base, base + 1, base + 2), (base, base + 2, base + 3)]
    mesh = Mesh(np.array(verts), np.array(norms), np.array(tris, dtype=np.int32))
    if not caps:
        return mesh
    parts = [mesh]
    if r0 > 0:
        parts.append(disc(r0, sides).transformed(np.diag([1.0, -1.0, -1.0]), (0, 0, z0)))
    if r1 > 0:
        parts.append(disc(r1, sides).moved((0, 0, z1)))
    return concat(parts)


def cylinder(
    radius: float, length: float, sides: int = 32, *, smooth: bool = True, caps: bool = True
) -> Mesh:
    """Cylinder of ``length`` centred on the origin, axis +z."""
    return frustum(radius, radius, -length / 2, length / 2, sides, smooth=smooth, caps=caps)


def disc(radius: float, sides: int = 32) -> Mesh:
    """Flat disc in the xy plane, normal +z."""
    ang = np.linspace(0.0, 2 * np.pi, sides, endpoint=False)
    verts = np.vstack([[0.0, 0.0, 0.0], np.c_[radius * np.cos(ang), radius * np.sin(ang), np.zeros(sides)]])
    tris = np.array([(0, 1 + i, 1 + (i + 1) % sides) for i in range(sides)], dtype=np.int32)
    return Mesh(verts, np.tile([0.0, 0.0, 1.0], (sides + 1, 1)), tris)


def dish(radius: float, depth: float, rings: int = 10, sides: int = 48) -> Mesh:
    """Paraboloid shell z = depth·(r/R)², opening towards +z (the concave side)."""
    rs = radius * np.sqrt(np.linspace(0.0, 1.0, rings + 1))  # equal-area rings
    ang = np.linspace(0.0, 2 * np.pi, sides, endpoint=False)
    rr, aa = np.meshgrid(rs, ang, indexing="ij")
    z = depth * (rr / radius) ** 2
    verts = np.stack([rr * np.cos(aa), rr * np.sin(aa), z], axis=-1).reshape(-1, 3)
    dzdr = 2.0 * depth * rr / radius**2
    norms = _unit(np.stack([-dzdr * np.cos(aa), -dzdr * np.sin(aa), np.ones_like(rr)], axis=-1))
    norms = norms.reshape(-1, 3)
    tris = []
    for i in range(rings):
        for j in range(sides):
            a, b = i * sides + j, i * sides + (j + 1) % sides
            c, d = a + sides, b + sides
            tris += [(a, c, d), (a, d, b)]
    return Mesh(verts, norms, np.array(tris, dtype=np.int32))


def sphere(radius: float, rings: int = 12, sides: int = 24) -> Mesh:
    th = np.linspace(0.0, np.pi, rings + 1)
    ph = np.linspace(0.0, 2 * np.pi, sides, endpoint=False)
    tt, pp = np.meshgrid(th, ph, indexing="ij")
    n = np.stack([np.sin(tt) * np.cos(pp), np.sin(tt) * np.sin(pp), np.cos(tt)], axis=-1).reshape(-1, 3)
    tris = []
    for i in range(rings):
        for j in range(sides):
            a, b = i * sides + j, i * sides + (j + 1) % sides
            tris += [(a, a + sides, b + sides), (a, b + sides, b)]
    return Mesh(radius * n, n, np.array(tris, dtype=np.int32))


def rod(p0: Vec, p1: Vec, radius: float, sides: int = 12, *, smooth: bool = True) -> Mesh:
    """A cylinder from point ``p0`` to point ``p1`` (booms, struts, masts)."""
    a, b = np.asarray(p0, dtype=np.float64), np.asarray(p1, dtype=np.float64)
    length = float(np.linalg.norm(b - a))
    return cylinder(radius, length, sides, smooth=smooth).transformed(align_z(b - a), (a + b) / 2)


def panel(width: float, height: float, thickness: float, center: Vec, rot: np.ndarray | None = None) -> Mesh:
    """A thin flat plate (solar array blanket, radiator) of width x height in its local xz plane."""
    return box((width, thickness, height)).transformed(rot, center)
