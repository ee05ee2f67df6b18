"""Procedural geometry of the Sponza-style atrium and of the default objects (pure numpy).

Conventions: right-handed, +Y up, metres. Every room mesh is a triangle soup (float64 here,
float32 on disk) whose face winding gives the normal ``cross(v1 - v0, v2 - v0)`` pointing
**into the room** (the visible side). Only surfaces that can be seen from inside the room are
built (no hidden faces inside walls or slabs), so a point sampled uniformly by area on the
meshes is always a visible surface point, and the room is closed: every ray from inside hits a
surface (``tests/test_scene.py`` checks it with random rays).

Layout (x along the courtyard, z across it): building x ∈ [−15, 15], z ∈ [−7, 7]. The open
courtyard is z ∈ [−3.7, 3.7], y ∈ [0, 12], roofed at y = 12 by a skylight (emissive panels
between dark beams). Two column-line walls (0.6 m thick, centred at z = ±4) carry ten arched
bays each on two storeys (lower openings y ∈ [0, 3.5] + semicircle r = 1.2; upper openings
y ∈ [5.4, 8.4] + semicircle); behind them the galleries z ∈ ±[4.3, 7] with a floor slab
(underside y = 5.0, top y = 5.4) and a ceiling at y = 10. Coloured drapes hang in some upper
openings; a small, very bright "sun" sphere under the skylight and warm lamps in the lower
galleries complete the lighting.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# --------------------------------------------------------------------------- layout constants
X0, X1 = -15.0, 15.0          # end walls
Z_BACK = 7.0                  # gallery back walls at z = ±7
Z_FRONT = 3.7                 # courtyard face of the column-line walls
Z_REAR = 4.3                  # gallery face of the column-line walls
Y_ROOF = 12.0
Y_SLAB_LO, Y_SLAB_HI = 5.0, 5.4
Y_GAL_CEIL = 10.0
BAY = 3.0
N_BAYS = 10
ARCH_R = 1.2
SPRING_LO, SPRING_HI = 3.5, 8.4   # arch springing heights (lower / upper storey)
Y_SPANDREL_TOP = 10.4             # courtyard face: top of the upper spandrel band


@dataclass
class Mesh:
    """A named triangle soup with a diffuse albedo and an emitted radiance (linear RGB)."""

    name: str
    vertices: np.ndarray           # (3F, 3) float64, 3 per triangle
    albedo: tuple
    emission: tuple = (0.0, 0.0, 0.0)
    normals: np.ndarray | None = None   # optional per-vertex normals (objects only)
    faces: np.ndarray | None = None     # optional indexed faces (objects only)

    @property
    def triangles(self) -> np.ndarray:
        """(F, 3, 3) corner positions."""
        if self.faces is not None:
            return self.vertices[self.faces]
        return self.vertices.reshape(-1, 3, 3)


class Builder:
    """Collects triangles; ``tri``/``quad`` flip the winding so the normal agrees with a hint."""

    def __init__(self) -> None:
        self.tris: list[np.ndarray] = []

    def tri(self, a, b, c, n_hint) -> None:
        a, b, c = (np.asarray(p, dtype=np.float64) for p in (a, b, c))
        n = np.cross(b - a, c - a)
        if np.linalg.norm(n) < 1e-12:
            return  # degenerate (e.g. a zero-width sliver): skip
        if np.dot(n, n_hint) < 0:
            b, c = c, b
        self.tris.append(np.stack([a, b, c]))

    def quad(self, a, b, c, d, n_hint) -> None:
        """Quad a-b-c-d (in order around its boundary)."""
        self.tri(a, b, c, n_hint)
        self.tri(a, c, d, n_hint)

    def array(self) -> np.ndarray:
        if not self.tris:
            return np.zeros((0, 3), np.float64)
        return np.concatenate(self.tris, axis=0)


def _grid_rect(b: Builder, plane: str, c: float, u_breaks, v_breaks, n_hint, keep=None) -> None:
    """Axis-aligned rectangle on ``plane`` ('xz' at y=c, 'xy' at z=c, 'zy' at x=c) split at the
    given breakpoints (shared with neighbouring meshes: no T-junctions); ``keep(u0,u1,v0,v1)``
    may drop cells."""
    for u0, u1 in zip(u_breaks[:-1], u_breaks[1:]):
        for v0, v1 in zip(v_breaks[:-1], v_breaks[1:]):
            if keep is not None and not keep(u0, u1, v0, v1):
                continue
            if plane == "xz":
                pts = [(u0, c, v0), (u1, c, v0), (u1, c, v1), (u0, c, v1)]
            elif plane == "xy":
                pts = [(u0, v0, c), (u1, v0, c), (u1, v1, c), (u0, v1, c)]
            else:  # "zy"
                pts = [(c, v0, u0), (c, v0, u1), (c, v1, u1), (c, v1, u0)]
            b.quad(*pts, n_hint)


def _bay_x(k: int) -> tuple[float, float, float]:
    x0 = X0 + BAY * k
    return x0, x0 + BAY, x0 + BAY / 2


def x_breaks() -> list[float]:
    """x breakpoints shared by every mesh running along the courtyard."""
    xs = set()
    for k in range(N_BAYS):
        x0, x1, xm = _bay_x(k)
        xs.update([round(x0, 9), round(x1, 9), round(xm - ARCH_R, 9), round(xm + ARCH_R, 9)])
    return sorted(xs)


def _in_opening(u0: float, u1: float) -> bool:
    """True when the x-cell [u0,u1] lies inside an arch opening (not a column strip)."""
    xm = X0 + BAY * (np.floor((0.5 * (u0 + u1) - X0) / BAY) + 0.5)
    return u0 >= xm - ARCH_R - 1e-9 and u1 <= xm + ARCH_R + 1e-9


def arch_angles(n_arc: int) -> np.ndarray:
    """Angles (0..π) of the arch polyline: uniform steps plus every spandrel corner angle, so the
    faces and the intrados share their vertices."""
    ang = set(np.round(np.linspace(0.0, np.pi, n_arc + 1), 12).tolist())
    for top in (Y_SLAB_HI - SPRING_LO, Y_SLAB_LO - SPRING_LO, Y_SPANDREL_TOP - SPRING_HI, Y_GAL_CEIL - SPRING_HI):
        ang.add(round(float(np.arctan2(top, BAY / 2)), 12))
        ang.add(round(float(np.arctan2(top, -BAY / 2)), 12))
    return np.array(sorted(ang))


def _spandrel(b: Builder, z: float, x0: float, x1: float, xm: float, yc: float, ytop: float,
              angles: np.ndarray, n_hint) -> None:
    """Face (at depth z) of the rectangle [x0,x1]×[yc,ytop] minus the half disc (xm,yc,R):
    a star-shaped region around the arch centre, meshed between the arc and the rectangle."""
    def boundary(t):
        c, s = np.cos(t), np.sin(t)
        ts = []
        if c > 1e-12:
            ts.append((x1 - xm) / c)
        if c < -1e-12:
            ts.append((x0 - xm) / c)
        if s > 1e-12:
            ts.append((ytop - yc) / s)
        r = min(ts)
        return (xm + r * c, yc + r * s, z)

    for t0, t1 in zip(angles[:-1], angles[1:]):
        p0 = (xm + ARCH_R * np.cos(t0), yc + ARCH_R * np.sin(t0), z)
        p1 = (xm + ARCH_R * np.cos(t1), yc + ARCH_R * np.sin(t1), z)
        q0, q1 = boundary(t0), boundary(t1)
        # the boundary may turn a corner between t0 and t1 only at a listed corner angle
        b.quad(p0, q0, q1, p1, n_hint)


def column_wall(side: int, n_arc: int) -> np.ndarray:
    """The column-line wall at z = side·4: both faces with the arched openings, jambs, intrados
    and sills. ``side`` = +1 or −1."""
    b = Builder()
    zf, zr = side * Z_FRONT, side * Z_REAR
    nf, nr = np.array([0, 0, -side], float), np.array([0, 0, side], float)
    angles = arch_angles(n_arc)
    for k in range(N_BAYS):
        x0, x1, xm = _bay_x(k)
        xa, xb = xm - ARCH_R, xm + ARCH_R
        for z, nh, lo_top, hi_top, top_band in ((zf, nf, Y_SLAB_HI, Y_SPANDREL_TOP, True),
                                                 (zr, nr, Y_SLAB_LO, Y_GAL_CEIL, False)):
            # column strips of both storeys
            for (ya, yb) in ((0.0, SPRING_LO), (Y_SLAB_HI, SPRING_HI)):
                b.quad((x0, ya, z), (xa, ya, z), (xa, yb, z), (x0, yb, z), nh)
                b.quad((xb, ya, z), (x1, ya, z), (x1, yb, z), (xb, yb, z), nh)
            _spandrel(b, z, x0, x1, xm, SPRING_LO, lo_top, angles, nh)
            _spandrel(b, z, x0, x1, xm, SPRING_HI, hi_top, angles, nh)
            if top_band:
                b.quad((x0, Y_SPANDREL_TOP, z), (x1, Y_SPANDREL_TOP, z), (x1, Y_ROOF, z), (x0, Y_ROOF, z), nh)
        # jambs, intrados, upper sill (inside the wall thickness)
        for (ya, yc) in ((0.0, SPRING_LO), (Y_SLAB_HI, SPRING_HI)):
            b.quad((xa, ya, zf), (xa, ya, zr), (xa, yc, zr), (xa, yc, zf), np.array([1.0, 0, 0]))
            b.quad((xb, ya, zf), (xb, ya, zr), (xb, yc, zr), (xb, yc, zf), np.array([-1.0, 0, 0]))
            for t0, t1 in zip(angles[:-1], angles[1:]):
                p = [(xm + ARCH_R * np.cos(t), yc + ARCH_R * np.sin(t)) for t in (t0, t1)]
                tm = 0.5 * (t0 + t1)
                nh = -np.array([np.cos(tm), np.sin(tm), 0.0])
                b.quad((*p[0], zf), (*p[0], zr), (*p[1], zr), (*p[1], zf), nh)
        b.quad((xa, Y_SLAB_HI, zf), (xb, Y_SLAB_HI, zf), (xb, Y_SLAB_HI, zr), (xa, Y_SLAB_HI, zr),
               np.array([0, 1.0, 0]))
    return b.array()


def room_shell() -> dict[str, np.ndarray]:
    """Floor, end walls, gallery back walls, slabs, gallery ceilings (triangle soups)."""
    xs = x_breaks()
    zs_all = [-Z_BACK, -Z_REAR, -Z_FRONT, Z_FRONT, Z_REAR, Z_BACK]
    out = {}
    b = Builder()  # floor: everything but the wall footprints outside the openings

    def keep_floor(u0, u1, v0, v1):
        in_wall = abs(abs(0.5 * (v0 + v1)) - 0.5 * (Z_FRONT + Z_REAR)) < 0.5 * (Z_REAR - Z_FRONT) + 1e-9
        return (not in_wall) or _in_opening(u0, u1)
    _grid_rect(b, "xz", 0.0, xs, zs_all, np.array([0, 1.0, 0]), keep_floor)
    out["floor"] = b.array()

    b = Builder()
    ys = [0.0, SPRING_LO, Y_SLAB_LO, Y_SLAB_HI, SPRING_HI, Y_GAL_CEIL, Y_SPANDREL_TOP, Y_ROOF]

    def keep_end(u0, u1, v0, v1):
        zc, yc = abs(0.5 * (u0 + u1)), 0.5 * (v0 + v1)
        if zc < Z_FRONT:
            return True                   # courtyard: full height
        if zc < Z_REAR:
            return False                  # the column-line wall touches the end wall
        return yc < Y_SLAB_LO or (Y_SLAB_HI < yc < Y_GAL_CEIL)
    for xw, nx in ((X0, 1.0), (X1, -1.0)):
        _grid_rect(b, "zy", xw, zs_all, ys, np.array([nx, 0, 0]), keep_end)
    out["end_walls"] = b.array()

    b = Builder()
    for s in (1, -1):
        _grid_rect(b, "xy", s * Z_BACK, xs, [0.0, SPRING_LO, Y_SLAB_LO], np.array([0, 0, -s]))
        _grid_rect(b, "xy", s * Z_BACK, xs, [Y_SLAB_HI, SPRING_HI, Y_GAL_CEIL], np.array([0, 0, -s]))
    out["gallery_walls"] = b.array()

    b = Builder()
    for s in (1, -1):
        zz = sorted([s * Z_REAR, s * Z_BACK])
        _grid_rect(b, "xz", Y_SLAB_LO, xs, zz, np.array([0, -1.0, 0]))
        _grid_rect(b, "xz", Y_GAL_CEIL, xs, zz, np.array([0, -1.0, 0]))
    out["gallery_ceilings"] = b.array()

    b = Builder()
    for s in (1, -1):
        zz = sorted([s * Z_REAR, s * Z_BACK])
        _grid_rect(b, "xz", Y_SLAB_HI, xs, zz, np.array([0, 1.0, 0]))
    out["gallery_floors"] = b.array()
    return out


SUN_SLOT = 3                       # roof bay whose skylight panel is replaced by the sun's opening
SUN_OPENING_Z = 1.0               # the opening spans z ∈ [−1, 1] (x as the panel)
SHAFT_LEAN = (-0.25, 1.0, -0.25)  # the light shaft rises along this vector (sunlight travels the other way)
SHAFT_HEIGHT = 12.0               # vertical height of the shaft above the roof


def roof(panel_margin: float = 0.15, panel_z: float = 3.4) -> tuple[np.ndarray, list[tuple[int, np.ndarray]], np.ndarray]:
    """(beams, [(k, panel_k)], shaft): the y = 12 ceiling over the courtyard, normals down.
    Panel k spans x ∈ [x0+m, x1−m], z ∈ [−panel_z, panel_z]; the beams fill the rest. Bay
    ``SUN_SLOT`` has no panel but an opening (z ∈ ±SUN_OPENING_Z) into a closed, slanted light
    shaft with the sun at its top. The shaft's walls are sky: albedo 0, emitting the mean
    skylight radiance (so they neither glow from the sun nor add noise). The sun's light enters
    the courtyard as one slanted beam and falls as a sunlit patch on the floor, the +z wall and
    the drapes."""
    xs = x_breaks()
    us = sorted(set(xs) | {round(X0 + BAY * k + d, 9) for k in range(N_BAYS) for d in (panel_margin, BAY - panel_margin)})
    vs = [-Z_FRONT, -panel_z, -SUN_OPENING_Z, SUN_OPENING_Z, panel_z, Z_FRONT]
    down = np.array([0, -1.0, 0])

    def slot(u0, u1):
        k = int(np.floor((0.5 * (u0 + u1) - X0) / BAY))
        x0 = X0 + BAY * k
        return k, (u0 >= x0 + panel_margin - 1e-9 and u1 <= x0 + BAY - panel_margin + 1e-9)

    def is_open(u0, u1, v0, v1):
        k, inner = slot(u0, u1)
        if not inner:
            return False
        if k == SUN_SLOT:
            return v0 >= -SUN_OPENING_Z - 1e-9 and v1 <= SUN_OPENING_Z + 1e-9
        return v0 >= -panel_z - 1e-9 and v1 <= panel_z + 1e-9
    b = Builder()
    _grid_rect(b, "xz", Y_ROOF, us, vs, down, lambda *c: not is_open(*c))
    panels = []
    for k in range(N_BAYS):
        if k == SUN_SLOT:
            continue
        x0 = X0 + BAY * k
        pb = Builder()
        _grid_rect(pb, "xz", Y_ROOF, [u for u in us if x0 + panel_margin - 1e-9 <= u <= x0 + BAY - panel_margin + 1e-9],
                   [v for v in vs if -panel_z - 1e-9 <= v <= panel_z + 1e-9], down)
        panels.append((k, pb.array()))
    return b.array(), panels, light_shaft(panel_margin)


def sun_opening(panel_margin: float = 0.15) -> tuple[float, float, float, float]:
    x0 = X0 + BAY * SUN_SLOT
    return x0 + panel_margin, x0 + BAY - panel_margin, -SUN_OPENING_Z, SUN_OPENING_Z


def shaft_top_offset() -> np.ndarray:
    lean = np.asarray(SHAFT_LEAN, float)
    return lean * (SHAFT_HEIGHT / lean[1])


def sun_center(sun_radius: float) -> np.ndarray:
    """Centre of the sun sphere: the middle of the shaft's top, one diameter below the cap."""
    xa, xb, za, zb = sun_opening()
    top = np.array([0.5 * (xa + xb), Y_ROOF, 0.5 * (za + zb)]) + shaft_top_offset()
    lean = np.asarray(SHAFT_LEAN, float)
    return top - 2.0 * sun_radius * lean / np.linalg.norm(lean)


def light_shaft(panel_margin: float = 0.15) -> np.ndarray:
    """The slanted parallelepiped above the sun's opening: four side walls and a cap, inwards."""
    xa, xb, za, zb = sun_opening(panel_margin)
    off = shaft_top_offset()
    bot = [np.array(p) for p in ((xa, Y_ROOF, za), (xb, Y_ROOF, za), (xb, Y_ROOF, zb), (xa, Y_ROOF, zb))]
    top = [p + off for p in bot]
    centre_bot = 0.25 * (bot[0] + bot[1] + bot[2] + bot[3])
    b = Builder()
    n_seg = 4  # split along the shaft so the triangles stay small-ish
    for i in range(4):
        j = (i + 1) % 4
        for s in range(n_seg):
            t0, t1 = s / n_seg, (s + 1) / n_seg
            a0, a1 = bot[i] + t0 * off, bot[j] + t0 * off
            c0, c1 = bot[i] + t1 * off, bot[j] + t1 * off
            mid = 0.25 * (a0 + a1 + c0 + c1)
            b.quad(a0, a1, c1, c0, centre_bot + 0.5 * (t0 + t1) * off - mid)
    b.quad(top[0], top[1], top[2], top[3], np.array([0, -1.0, 0]))
    return b.array()


def drape(side: int, k: int, n_u: int = 24, n_v: int = 4, thickness: float = 0.02,
          amplitude: float = 0.08, waves: float = 3.0) -> np.ndarray:
    """A closed thin wavy slab hanging in the upper opening of bay k on wall ``side``
    (x ∈ [xm−1.05, xm+1.05], y ∈ [6.0, 9.3], waving in z around the wall's mid-plane)."""
    _, _, xm = _bay_x(k)
    xa, xb, ya, yb = xm - 1.05, xm + 1.05, 6.0, 9.3
    zc = side * 0.5 * (Z_FRONT + Z_REAR)
    us = np.linspace(0.0, 1.0, n_u + 1)
    vs = np.linspace(0.0, 1.0, n_v + 1)
    x = xa + (xb - xa) * us
    wave = amplitude * np.sin(2 * np.pi * waves * us)
    b = Builder()
    for sheet, off in ((-1, -0.5 * thickness), (1, 0.5 * thickness)):  # -1: courtyard side
        nz_sign = -side if sheet < 0 else side
        z = zc + side * off + wave
        for i in range(n_u):
            dzdx = (z[i + 1] - z[i]) / (x[i + 1] - x[i])
            nh = np.array([-dzdx * nz_sign, 0.0, float(nz_sign)])
            for j in range(n_v):
                y0, y1 = ya + (yb - ya) * vs[j], ya + (yb - ya) * vs[j + 1]
                b.quad((x[i], y0, z[i]), (x[i + 1], y0, z[i + 1]), (x[i + 1], y1, z[i + 1]), (x[i], y1, z[i]), nh)
    zf = zc - side * 0.5 * thickness + wave
    zr = zc + side * 0.5 * thickness + wave
    for i in range(n_u):  # bottom and top edges
        b.quad((x[i], ya, zf[i]), (x[i + 1], ya, zf[i + 1]), (x[i + 1], ya, zr[i + 1]), (x[i], ya, zr[i]), np.array([0, -1.0, 0]))
        b.quad((x[i], yb, zf[i]), (x[i + 1], yb, zf[i + 1]), (x[i + 1], yb, zr[i + 1]), (x[i], yb, zr[i]), np.array([0, 1.0, 0]))
    for xi, i, nx in ((xa, 0, -1.0), (xb, n_u, 1.0)):  # side edges
        b.quad((xi, ya, zf[i]), (xi, ya, zr[i]), (xi, yb, zr[i]), (xi, yb, zf[i]), np.array([nx, 0, 0]))
    return b.array()


def icosphere(subdiv: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere: (V, 3) float64 vertices, (F, 3) int32 faces wound outwards."""
    t = (1.0 + 5 ** 0.5) / 2
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
         (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
         (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5),
         (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    verts = [np.array(p, float) / np.linalg.norm(p) for p in v]
    faces = list(f)
    for _ in range(subdiv):
        cache: dict[tuple[int, int], int] = {}

        def mid(i, j):
            key = (min(i, j), max(i, j))
            if key not in cache:
                m = verts[i] + verts[j]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]
        nf = []
        for a, b_, c in faces:
            ab, bc, ca = mid(a, b_), mid(b_, c), mid(c, a)
            nf += [(a, ab, ca), (b_, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = nf
    V = np.array(verts)
    F = np.array(faces, dtype=np.int32)
    # make sure every face winds outwards
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    flip = np.sum(n * V[F].mean(axis=1), axis=1) < 0
    F[flip] = F[flip][:, [0, 2, 1]]
    return V, F


def sphere_soup(center, radius: float, subdiv: int) -> np.ndarray:
    V, F = icosphere(subdiv)
    return (V[F] * radius + np.asarray(center, float)).reshape(-1, 3)


# --------------------------------------------------------------------------- the room
@dataclass
class AtriumParams:
    """Radiometry of the atrium (linear RGB radiance, W·sr⁻¹·m⁻² up to an arbitrary scale)."""

    sky_radiance: float = 2.0
    sky_gradient: float = 0.5          # panel k radiance × (1 − g/2 + g·k/9): brighter towards +x
    sky_color: tuple = (0.85, 0.92, 1.0)
    sun_radiance: float = 1.5e5
    sun_radius: float = 0.4
    sun_color: tuple = (1.0, 0.93, 0.82)
    lamp_radiance: float = 40.0
    lamp_radius: float = 0.12
    lamp_color: tuple = (1.0, 0.72, 0.42)
    n_arc: int = 12
    albedos: dict = field(default_factory=lambda: {
        "floor": (0.42, 0.37, 0.30), "end_walls": (0.55, 0.50, 0.42), "gallery_walls": (0.20, 0.17, 0.14),
        "gallery_ceilings": (0.35, 0.32, 0.28), "gallery_floors": (0.40, 0.36, 0.30),
        "column_walls": (0.70, 0.64, 0.54), "roof_beams": (0.05, 0.05, 0.05), "light_shaft": (0.0, 0.0, 0.0), "skylight": (0.80, 0.80, 0.80),
        "sun": (0.80, 0.80, 0.80), "lamps": (0.80, 0.80, 0.80),
        "drape_red": (0.65, 0.06, 0.05), "drape_green": (0.07, 0.45, 0.09), "drape_blue": (0.05, 0.09, 0.60)})


LAMP_POSITIONS = [(x, 4.3, s * 5.65) for s in (1, -1) for x in (-10.5, -1.5, 7.5)]
DRAPES = [(1, k, c) for k, c in zip((1, 3, 5, 7), ("red", "green", "blue", "red"))] + \
         [(-1, k, c) for k, c in zip((2, 4, 6, 8), ("green", "blue", "red", "green"))]


def atrium(p: AtriumParams) -> list[Mesh]:
    """All meshes of the room, in a fixed order."""
    A = p.albedos
    meshes = [Mesh(name, soup, A[name]) for name, soup in room_shell().items()]
    walls = np.concatenate([column_wall(1, p.n_arc), column_wall(-1, p.n_arc)])
    meshes.append(Mesh("column_walls", walls, A["column_walls"]))
    beams, panels, shaft = roof()
    meshes.append(Mesh("roof_beams", beams, A["roof_beams"]))
    sky_mean = p.sky_radiance  # the panels' radiance factors average to 1
    meshes.append(Mesh("light_shaft", shaft, A["light_shaft"], tuple(sky_mean * c for c in p.sky_color)))
    for k, soup in panels:
        f = p.sky_radiance * (1.0 - p.sky_gradient / 2 + p.sky_gradient * k / (N_BAYS - 1))
        meshes.append(Mesh(f"skylight_{k:02d}", soup, A["skylight"], tuple(f * c for c in p.sky_color)))
    for colour in ("red", "green", "blue"):
        soup = np.concatenate([drape(s, k) for s, k, c in DRAPES if c == colour])
        meshes.append(Mesh(f"drape_{colour}", soup, A[f"drape_{colour}"]))
    meshes.append(Mesh("sun", sphere_soup(sun_center(p.sun_radius), p.sun_radius, 2), A["sun"],
                       tuple(p.sun_radiance * c for c in p.sun_color)))
    lamps = np.concatenate([sphere_soup(c, p.lamp_radius, 1) for c in LAMP_POSITIONS])
    meshes.append(Mesh("lamps", lamps, A["lamps"], tuple(p.lamp_radiance * c for c in p.lamp_color)))
    return meshes


# --------------------------------------------------------------------------- the lamp room
LAMP_ROOM = ((-8.0, 0.0, -6.0), (8.0, 5.0, 6.0))   # interior box [m]
LAMP_ROOM_LAMPS = [(-5.0, 4.4, -3.5), (0.5, 4.4, -4.0), (5.5, 4.4, -2.5), (-4.0, 4.4, 3.5), (1.0, 4.4, 4.0),
                   (5.0, 4.4, 3.0)]


@dataclass
class LampRoomParams:
    """A closed box room lit only by small, very bright lamps (the case where splat models
    fail): walls 10³–10⁴ × darker than the lamps (measured in the make-scene log)."""

    lamp_radiance: float = 5000.0
    lamp_radius: float = 0.04
    lamp_color: tuple = (1.0, 0.85, 0.65)
    albedos: dict = field(default_factory=lambda: {
        "floor": (0.40, 0.36, 0.30), "ceiling": (0.75, 0.75, 0.72), "walls": (0.60, 0.58, 0.55),
        "wall_red": (0.60, 0.10, 0.08), "wall_green": (0.10, 0.45, 0.12), "lamps": (0.80, 0.80, 0.80)})


def lamp_room(p: LampRoomParams) -> list[Mesh]:
    """The lamp room's meshes (inward faces on a 1 m grid), in a fixed order: floor, ceiling,
    walls (−x red, +x green, the z walls grey), lamps (spheres of ``lamp_radius``)."""
    (x0, y0, z0), (x1, y1, z1) = LAMP_ROOM
    xs, ys, zs = (np.linspace(a, b, int(round(b - a)) + 1) for a, b in ((x0, x1), (y0, y1), (z0, z1)))
    A = p.albedos
    out = []
    for name, plane, c, u, v, n in (("floor", "xz", y0, xs, zs, (0, 1, 0)), ("ceiling", "xz", y1, xs, zs, (0, -1, 0)),
                                    ("wall_red", "zy", x0, zs, ys, (1, 0, 0)), ("wall_green", "zy", x1, zs, ys, (-1, 0, 0))):
        b = Builder()
        _grid_rect(b, plane, c, u, v, np.array(n, float))
        out.append(Mesh(name, b.array(), A[name]))
    b = Builder()
    for zc, nz in ((z0, 1.0), (z1, -1.0)):
        _grid_rect(b, "xy", zc, xs, ys, np.array([0, 0, nz]))
    out.append(Mesh("walls", b.array(), A["walls"]))
    lamps = np.concatenate([sphere_soup(c, p.lamp_radius, 1) for c in LAMP_ROOM_LAMPS])
    out.append(Mesh("lamps", lamps, A["lamps"], tuple(p.lamp_radiance * c for c in p.lamp_color)))
    return out


def room_box(room: str) -> tuple[np.ndarray, np.ndarray]:
    """The open interior box of a room where the object and the cameras may stand (lo, hi) [m]:
    the atrium's courtyard, or the lamp room."""
    if room == "atrium":
        return np.array([X0, 0.0, -Z_FRONT]), np.array([X1, Y_ROOF, Z_FRONT])
    return np.array(LAMP_ROOM[0]), np.array(LAMP_ROOM[1])


# --------------------------------------------------------------------------- objects (unit size, local frame)
def object_sphere(subdiv: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit sphere (V, F, smooth normals)."""
    V, F = icosphere(subdiv)
    return V, F, V.copy()


def object_knot(n_u: int = 256, n_v: int = 24, tube: float = 0.42) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A (2,3) torus knot tube (self-shadowing, interreflecting), scaled so its bounding sphere
    about the origin has radius 1. Returns (V, F, smooth normals) with outward faces."""
    t = np.linspace(0, 2 * np.pi, n_u, endpoint=False)

    def curve(t):
        r = 2.0 + np.cos(3 * t)
        return np.stack([r * np.cos(2 * t), np.sin(3 * t), r * np.sin(2 * t)], axis=-1)
    c = curve(t)
    d = curve(t + 1e-4) - curve(t - 1e-4)
    T = d / np.linalg.norm(d, axis=1, keepdims=True)
    # rotation-minimising frame (double reflection, Wang et al. 2008), closed up by a twist fix
    N = np.zeros_like(T)
    ref = np.array([0.0, 1.0, 0.0])
    N[0] = np.cross(T[0], ref)
    N[0] /= np.linalg.norm(N[0])
    for i in range(n_u - 1):
        v1 = c[i + 1] - c[i]
        c1 = v1 @ v1
        rL = N[i] - (2 / c1) * (v1 @ N[i]) * v1
        tL = T[i] - (2 / c1) * (v1 @ T[i]) * v1
        v2 = T[i + 1] - tL
        c2 = v2 @ v2
        N[i + 1] = rL - (2 / c2) * (v2 @ rL) * v2 if c2 > 1e-20 else rL
        N[i + 1] /= np.linalg.norm(N[i + 1])
    # distribute the closing twist
    v1 = c[0] - c[-1]
    c1 = v1 @ v1
    rL = N[-1] - (2 / c1) * (v1 @ N[-1]) * v1
    tL = T[-1] - (2 / c1) * (v1 @ T[-1]) * v1
    v2 = T[0] - tL
    rL = rL - (2 / (v2 @ v2)) * (v2 @ rL) * v2
    B0 = np.cross(T[0], N[0])
    twist = np.arctan2(rL @ B0, rL @ N[0])
    B = np.cross(T, N)
    phi = -twist * np.arange(n_u) / n_u
    N, B = np.cos(phi)[:, None] * N + np.sin(phi)[:, None] * B, -np.sin(phi)[:, None] * N + np.cos(phi)[:, None] * B
    s = np.linspace(0, 2 * np.pi, n_v, endpoint=False)
    nrm = np.cos(s)[None, :, None] * N[:, None, :] + np.sin(s)[None, :, None] * B[:, None, :]
    V = c[:, None, :] + tube * nrm
    V = V.reshape(-1, 3)
    nrm = nrm.reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n_u), np.arange(n_v), indexing="ij")
    a = i * n_v + j
    b_ = ((i + 1) % n_u) * n_v + j
    c_ = ((i + 1) % n_u) * n_v + (j + 1) % n_v
    d_ = i * n_v + (j + 1) % n_v
    F = np.concatenate([np.stack([a, b_, c_], -1).reshape(-1, 3), np.stack([a, c_, d_], -1).reshape(-1, 3)]).astype(np.int32)
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    flip = np.sum(fn * nrm[F].mean(axis=1), axis=1) < 0
    F[flip] = F[flip][:, [0, 2, 1]]
    scale = 1.0 / np.linalg.norm(V, axis=1).max()
    return V * scale, F, nrm


def object_bowl(n_phi: int = 96, n_theta: int = 24, inner: float = 0.8,
                tilt_deg: float = 50.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A closed thick hemispherical bowl (strong self-shadowing inside and light between its walls): the outer
    hemisphere of radius 1, the flat rim, the inner hemisphere of radius ``inner``, revolved about Y, each with
    its own vertices and normals (sharp rim edges), outward faces; bounding sphere about the origin of radius 1.
    Its opening, +Y when upright, is tilted by ``tilt_deg`` about +Z towards −X (the side the presets' view1
    looks from, so that view1 sees inside). Returns (V, F, normals)."""
    phi = np.linspace(0, 2 * np.pi, n_phi, endpoint=False)
    Vs, Ns, Fs = [], [], []

    def surface(prof: np.ndarray, nprof: np.ndarray) -> None:
        # prof (k, 2) (r, y) and its normals (k, 2) (nr, ny), revolved; quads between consecutive rings
        k = len(prof)
        cph, sph = np.cos(phi), np.sin(phi)
        V = np.stack([prof[:, None, 0] * cph[None], np.broadcast_to(prof[:, None, 1], (k, n_phi)),
                      prof[:, None, 0] * sph[None]], -1).reshape(-1, 3)
        N = np.stack([nprof[:, None, 0] * cph[None], np.broadcast_to(nprof[:, None, 1], (k, n_phi)),
                      nprof[:, None, 0] * sph[None]], -1).reshape(-1, 3)
        i, j = np.meshgrid(np.arange(k - 1), np.arange(n_phi), indexing="ij")
        a, b = i * n_phi + j, i * n_phi + (j + 1) % n_phi
        c, d = (i + 1) * n_phi + (j + 1) % n_phi, (i + 1) * n_phi + j
        F = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
        off = sum(len(v) for v in Vs)
        Vs.append(V)
        Ns.append(N)
        Fs.append(F + off)

    th = np.linspace(0.0, np.pi / 2, n_theta)
    surface(np.stack([np.sin(th), -np.cos(th)], 1), np.stack([np.sin(th), -np.cos(th)], 1))           # outer
    surface(np.array([[1.0, 0.0], [inner, 0.0]]), np.array([[0.0, 1.0], [0.0, 1.0]]))                  # rim
    th2 = th[::-1]
    surface(np.stack([inner * np.sin(th2), -inner * np.cos(th2)], 1), np.stack([-np.sin(th2), np.cos(th2)], 1))
    V, N, F = np.concatenate(Vs), np.concatenate(Ns), np.concatenate(Fs).astype(np.int32)
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    flip = np.sum(fn * N[F].mean(axis=1), axis=1) < 0
    F[flip] = F[flip][:, [0, 2, 1]]
    ok = np.linalg.norm(fn, axis=1) > 1e-12                                  # the poles' degenerate triangles
    a = np.radians(tilt_deg)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    return V @ R.T, F[ok], N @ R.T


# --------------------------------------------------------------------------- area sampling
def triangle_areas(tris: np.ndarray) -> np.ndarray:
    return 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)


def sample_surface(tris: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` points uniform by area on the triangles (F,3,3): (points, face normals, face index)."""
    area = triangle_areas(tris)
    cdf = np.cumsum(area)
    cdf /= cdf[-1]
    f = np.searchsorted(cdf, rng.random(n), side="right")
    f = np.minimum(f, len(tris) - 1)
    u, v = rng.random(n), rng.random(n)
    su = np.sqrt(u)
    b0, b1 = 1 - su, su * (1 - v)
    t = tris[f]
    p = b0[:, None] * t[:, 0] + b1[:, None] * t[:, 1] + (1 - b0 - b1)[:, None] * t[:, 2]
    nrm = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return p, nrm, f


def two_rooms(n: int = 30000, seed: int = 3) -> tuple:
    """A closed 4×2×2 m box split by a full 2 cm thick wall at x = 2 into two closed rooms (each
    side of the wall sampled, facing its room); a bright ceiling patch in each room: (points (N,3) [m], colours (N,3)
    linear, room A's patch (N,) bool, room B's patch, normals (N,3)) — render-cubemaps' visibility test scene."""
    rng = np.random.default_rng(seed)
    quads = [  # (origin, u, v) rectangles
        ((0, 0, 0), (4, 0, 0), (0, 0, 2)), ((0, 2, 0), (4, 0, 0), (0, 0, 2)),   # floor, ceiling
        ((0, 0, 0), (4, 0, 0), (0, 2, 0)), ((0, 0, 2), (4, 0, 0), (0, 2, 0)),   # z walls
        ((0, 0, 0), (0, 2, 0), (0, 0, 2)), ((4, 0, 0), (0, 2, 0), (0, 0, 2)),   # x walls
        ((1.99, 0, 0), (0, 2, 0), (0, 0, 2)), ((2.01, 0, 0), (0, 2, 0), (0, 0, 2)),  # the dividing wall's sides
    ]
    area = np.array([np.linalg.norm(np.cross(u, v)) for _, u, v in quads])
    cnt = rng.multinomial(n, area / area.sum())
    pts = []
    for (o, u, v), c in zip(quads, cnt):
        a, b = rng.uniform(size=(2, c))
        pts.append(np.asarray(o) + a[:, None] * np.asarray(u) + b[:, None] * np.asarray(v))
    pts = np.concatenate(pts)
    # inward normals: the outer walls face the box centre, each side of the dividing wall its room
    nrm = np.zeros_like(pts)
    for ax in range(3):
        on = np.isclose(pts[:, ax], 0.0) | np.isclose(pts[:, ax], (4.0, 2.0, 2.0)[ax])
        nrm[on, ax] = np.sign((2.0, 1.0, 1.0)[ax] - pts[on, ax])
    nrm[np.isclose(pts[:, 0], 1.99), 0] = -1.0
    nrm[np.isclose(pts[:, 0], 2.01), 0] = 1.0
    cols = np.full((len(pts), 3), 0.3)
    ceil = np.isclose(pts[:, 1], 2.0)
    pa = ceil & (pts[:, 0] > 0.5) & (pts[:, 0] < 1.5) & (pts[:, 2] > 0.5) & (pts[:, 2] < 1.5)
    pb = ceil & (pts[:, 0] > 2.5) & (pts[:, 0] < 3.5) & (pts[:, 2] > 0.5) & (pts[:, 2] < 1.5)
    cols[pa | pb] = 1.0
    return pts, cols, pa, pb, nrm
