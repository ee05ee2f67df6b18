"""build-bsh: the invariants of the bounding sphere hierarchy (seed 000 §5.1, §5.4), checked
against independent references (brute force over each node's points, a recursive radix-split
reference of the Karras tree, bit-by-bit Morton codes, brute-force minimum cones).

Float tolerance used for containment: the stored float32 centres/radii/cones are built so that
containment holds exactly in real arithmetic; the checks evaluate it in float64 and allow
1e-9 relative (distances) and 1e-9 rad (angles) for the float64 evaluation itself.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.bsh import tree as core
from pipeline.bsh.format import NODE_DTYPE, decode_cones
from pipeline.bsh.cones import pack_cones
from pipeline.bsh.build_bsh import BuildBshConfig
from pipeline.bsh.builder import SCHEMA, build_bsh, grid_origin
from pipeline.errors import ConfigError, InputError

DIST_TOL = 1e-9
ANG_TOL = 1e-9


# ----------------------------------------------------------------------------- clouds
def unit(v):
    v = np.asarray(v, dtype=np.float64)
    return (v / np.linalg.norm(v, axis=-1, keepdims=True)).astype(np.float32)


def random_cloud(n, seed=0, hemi=False):
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(n, 3)).astype(np.float32)
    nn = rng.normal(size=(n, 3))
    if hemi:
        nn[:, 1] = np.abs(nn[:, 1]) + 0.5
    return p, unit(nn), rng.random((n, 3)).astype(np.float32) * 3


def room_cloud(n, seed=0):
    """Points sampled uniformly by area on the inside of a 4 x 3 x 5 m box, normals inwards,
    colours smooth per wall plus noise."""
    rng = np.random.default_rng(seed)
    size = np.array([4.0, 3.0, 5.0])
    faces = []  # (axis, side)
    areas = []
    for ax in range(3):
        a = np.prod(np.delete(size, ax))
        for side in (0, 1):
            faces.append((ax, side))
            areas.append(a)
    areas = np.array(areas) / np.sum(areas)
    f = rng.choice(6, size=n, p=areas)
    p = rng.random((n, 3)) * size
    nn = np.zeros((n, 3))
    for k, (ax, side) in enumerate(faces):
        m = f == k
        p[m, ax] = side * size[ax]
        nn[m, ax] = 1.0 if side == 0 else -1.0
    c = 0.2 + 0.1 * f[:, None] * np.array([1.0, 0.5, 0.25]) + rng.normal(0, 0.02, (n, 3))
    return p.astype(np.float32), nn.astype(np.float32), np.abs(c).astype(np.float32)


def wall(nx, ny, spacing, color=(0.5, 0.4, 0.3), noise=0.0, seed=0, jitter=False):
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(nx) * spacing, np.arange(ny) * spacing, indexing="ij")
    p = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    if jitter:
        p[:, :2] += rng.random((x.size, 2)) * spacing
    nn = np.tile([0.0, 0.0, 1.0], (x.size, 1))
    c = np.tile(color, (x.size, 1)) + rng.normal(0, noise, (x.size, 3)) if noise else np.tile(color, (x.size, 1))
    return p.astype(np.float32), nn.astype(np.float32), np.abs(c).astype(np.float32)


# ----------------------------------------------------------------------------- references
def morton_reference(points, bits):
    """Bit-by-bit Morton codes of the cubed bounding box (x highest in each triple), the grid half a cell below
    the box's min corner (builder.grid_origin: cell k is centred on lo + k × side / 2^bits)."""
    p = points.astype(np.float64)
    lo = p.min(0)
    side = float(np.max(p.max(0) - lo)) or 1.0
    q = np.clip(np.floor((p - lo) * (2.0 ** bits / side) + 0.5), 0, 2 ** bits - 1).astype(np.uint64)
    code = np.zeros(len(p), dtype=np.uint64)
    for b in range(bits):
        for ax, off in ((0, 2), (1, 1), (2, 0)):
            code |= ((q[:, ax] >> np.uint64(b)) & np.uint64(1)) << np.uint64(3 * b + off)
    return code, q


def check_tree(r, points, normals, colors, *, check_colour=True):
    """Every invariant of the linearised tree, by brute force over each node's points."""
    M = len(r["radius"])
    N = len(points)
    child, first, count, order = r["child"], r["first"], r["count"], r["order"]
    assert sorted(order.tolist()) == list(range(N))
    assert first[0] == 0 and count[0] == N
    inner = child[:, 0] >= 0
    ii = np.flatnonzero(inner)
    # depth-first layout: left child next, right child after the left sub-tree
    assert np.all(child[ii, 0] == ii + 1)
    assert np.all(child[ii, 1] > ii + 1)
    nodes = r["nodes"]
    assert nodes.dtype.itemsize == 40
    assert np.all(nodes["right"][ii] == child[ii, 1])
    assert np.all(nodes["right"][~inner] == 0xFFFFFFFF)
    skip = nodes["skip"].astype(np.int64)
    assert np.all(skip[~inner] == np.flatnonzero(~inner) + 1)
    assert np.all(skip[ii] == skip[child[ii, 1]])
    assert np.all(child[ii, 1] == skip[ii + 1])
    assert skip[0] == M
    # every node reached exactly once by the stackless walk, in index order
    seen = []
    i = 0
    while i < M:
        seen.append(i)
        i = i + 1 if inner[i] else skip[i]
    assert seen == list(range(M))
    visits = np.zeros(M, dtype=np.int64)
    stack = [0]
    while stack:
        u = stack.pop()
        visits[u] += 1
        if inner[u]:
            stack += [child[u, 1], child[u, 0]]
    assert np.all(visits == 1)
    # ranges: children split the parent's points, leaves partition all points
    a, b = child[ii, 0], child[ii, 1]
    assert np.all(first[a] == first[ii])
    assert np.all(first[b] == first[ii] + count[a])
    assert np.all(count[ii] == count[a] + count[b])
    lv = np.flatnonzero(~inner)
    lv = lv[np.argsort(first[lv])]
    assert np.array_equal(first[lv], np.concatenate([[0], np.cumsum(count[lv])[:-1]]))
    assert count[lv].sum() == N and np.all(count > 0)
    # decoded arrays match the packed records
    assert np.array_equal(nodes["center"], r["center"]) and np.array_equal(nodes["radius"], r["radius"])
    assert np.array_equal(nodes["color"], r["color"])
    ax, half = decode_cones(nodes["cone"])
    assert np.allclose(ax, r["cone_axis"], atol=1e-6)
    assert np.all(r["cone_half_angle"].astype(np.float64) >= half - 1e-12)
    # parents contain their children's spheres
    c = r["center"].astype(np.float64)
    rad = r["radius"].astype(np.float64)
    for k in (a, b):
        d = np.linalg.norm(c[ii] - c[k], axis=1) + rad[k]
        assert np.all(d <= rad[ii] * (1 + DIST_TOL) + DIST_TOL * np.abs(c[ii]).max(initial=0)), \
            f"child sphere outside parent by {np.max(d - rad[ii]):.3g} m"
    # brute force over every (node, point of the node) pair, vectorised
    P = points.astype(np.float64)
    Nn = normals.astype(np.float64)
    Nn /= np.linalg.norm(Nn, axis=1, keepdims=True)
    C = colors.astype(np.float64)
    node = np.repeat(np.arange(M), count)
    starts = np.concatenate([[0], np.cumsum(count)[:-1]])
    pos = first[node] + np.arange(len(node)) - starts[node]
    idx = order[pos]
    # every point of a node (= of its sub-tree) lies in the node's sphere
    d = np.linalg.norm(P[idx] - c[node], axis=1)
    lim = rad[node] * (1 + DIST_TOL) + DIST_TOL * np.abs(c[node]).max(axis=1)
    assert np.all(d <= lim), f"point outside its node's sphere by {np.max(d - rad[node]):.3g} m"
    # every normal lies in the decoded cone (the float arrays and a float32 GLSL decode)
    g_ax, g_half = glsl_decode(nodes["cone"])
    for axv, hv in ((r["cone_axis"].astype(np.float64), r["cone_half_angle"].astype(np.float64)), (g_ax, g_half)):
        ang = np.arctan2(np.linalg.norm(np.cross(Nn[idx], axv[node]), axis=1), np.sum(Nn[idx] * axv[node], axis=1))
        assert np.all(ang <= hv[node] + ANG_TOL), f"normal outside its node's cone by {np.max(ang - hv[node]):.3g} rad"
    if check_colour:
        emit = np.zeros(N, bool)                 # the emitters' points count black (single-point voxels here:
        if len(r.get("emitters", ())):          # an emitter's centre is its point)
            from scipy.spatial import cKDTree

            d, j = cKDTree(P).query(r["emitters"][:, :3].astype(np.float64))
            assert np.all(d < 1e-5) and len(np.unique(j)) == len(j)
            emit[j] = True
            # a leaf of the tree made of emitters splats nothing
            el = lv[r["splat_radius"][lv] == 0]
            assert all(emit[order[first[i]:first[i] + count[i]]].all() for i in el)
        mean = np.add.reduceat(C[idx] * ~emit[idx][:, None], starts, axis=0) / count[:, None]
        assert np.allclose(r["color"], mean, rtol=2e-6, atol=1e-7 * max(1.0, np.abs(mean).max()))


def glsl_decode(packed):
    """pbgi_cone_decode of pipeline/pbgi_common.glsl, in float32 like the GPU."""
    p = packed.astype(np.uint32)
    c = np.stack([(p >> s) & 0xFF for s in (0, 8, 16, 24)], axis=1).astype(np.float32) / np.float32(255)
    a = c[:, :3] * np.float32(2) - np.float32(1)
    a = a / np.linalg.norm(a, axis=1, keepdims=True).astype(np.float32)
    half = np.where((p >> 24) == 255, np.float32(np.pi), c[:, 3] * np.float32(np.pi)).astype(np.float32)
    return a.astype(np.float64), half.astype(np.float64)


def radix_reference(codes):
    """Binary radix tree by recursive top-down splitting of the keys (code, index) at their
    highest differing bit: the tree Karras 2012 defines. Returns {(lo, hi): (left, right)}."""
    keys = [(int(c) << 64) | i for i, c in enumerate(codes)]
    out = {}

    def rec(a, b):
        if a == b:
            return
        p = (keys[a] ^ keys[b]).bit_length() - 1
        s = a
        while s + 1 <= b and not (keys[s + 1] >> p) & 1:
            s += 1
        out[(a, b)] = ((a, s), (s + 1, b))
        rec(a, s)
        rec(s + 1, b)

    rec(0, len(keys) - 1)
    return out


def brute_min_cone(v):
    """Smallest cap containing unit vectors v (in an open hemisphere): over all caps with 1, 2
    or 3 of them on the boundary."""
    v = v.astype(np.float64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    best = (None, np.inf)
    n = len(v)
    cands = [v[i] for i in range(n)]
    for i in range(n):
        for j in range(i + 1, n):
            m = v[i] + v[j]
            cands.append(m / np.linalg.norm(m))
            for k in range(j + 1, n):
                nrm = np.cross(v[j] - v[i], v[k] - v[i])
                if np.linalg.norm(nrm) < 1e-12:
                    continue
                nrm /= np.linalg.norm(nrm)
                cands += [nrm, -nrm]
    for u in cands:
        th = np.max(np.arctan2(np.linalg.norm(np.cross(v, u), axis=1), v @ u))
        if th < best[1]:
            best = (u, th)
    return best


# ----------------------------------------------------------------------------- unit pieces
def test_morton_codes_match_bitwise_reference():
    p, _, _ = random_cloud(2000, seed=3)
    for bits in (1, 5, 21):
        ref, _ = morton_reference(p, bits)
        lo = p.min(0).astype(np.float64)
        side = float(np.max(p.max(0).astype(np.float64) - lo))
        got = core.morton_codes(p, grid_origin(lo, side, bits), 2.0 ** bits / side, bits)
        assert np.array_equal(got, ref)


def test_radix_argsort_is_stable_sort():
    rng = np.random.default_rng(1)
    for hi in (2, 1000, 2 ** 63):
        k = rng.integers(0, hi, 5000, dtype=np.uint64)
        o, s = core.radix_argsort(k, 64)
        assert np.array_equal(o, np.argsort(k, kind="stable"))
        assert np.array_equal(s, np.sort(k))


@pytest.mark.parametrize("seed", range(6))
def test_karras_equals_recursive_radix_split(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 300))
    # small code range → many duplicate codes, broken by index
    codes = np.sort(rng.integers(0, [4, 50, 2 ** 20, 2 ** 63][seed % 4], n, dtype=np.uint64))
    left, right, rlo, rhi = core.karras_build(codes)
    m = n - 1

    def rng_of(u):
        return (u - m, u - m) if u >= m else (int(rlo[u]), int(rhi[u]))

    got = {(int(rlo[u]), int(rhi[u])): (rng_of(left[u]), rng_of(right[u])) for u in range(m)}
    assert got == radix_reference(codes)
    assert rlo[0] == 0 and rhi[0] == n - 1


@pytest.mark.parametrize("seed", range(40))
def test_min_cone_is_minimal_and_contains(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 8))
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2]) + 0.3 * (seed % 3)  # inside an open hemisphere
    v = unit(v)
    out = np.empty(4)
    core._min_cone(v, 0, n, out)
    u, th = brute_min_cone(v)
    ang = np.arctan2(np.linalg.norm(np.cross(v.astype(np.float64), out[:3]), axis=1), v.astype(np.float64) @ out[:3])
    assert ang.max() <= out[3] + 1e-15
    assert out[3] <= th + core.ANGLE_EPS + 1e-9


def test_min_cone_beyond_a_hemisphere_still_contains():
    rng = np.random.default_rng(5)
    v = unit(rng.normal(size=(300, 3)))
    out = np.empty(4)
    core._min_cone(v, 0, len(v), out)
    ang = np.arctan2(np.linalg.norm(np.cross(v.astype(np.float64), out[:3]), axis=1), v.astype(np.float64) @ out[:3])
    assert ang.max() <= out[3]


@pytest.mark.parametrize("seed", range(12))
def test_min_cone_ignores_order_and_duplicates(seed):
    """The same cone bit for bit for the vectors permuted, and each twice (a node of a duplicated cloud): the cap is
    re-solved from its support in a fixed order; vectors that fill more than a hemisphere give the sphere (+Z, π)."""
    rng = np.random.default_rng(100 + seed)
    n = int(rng.integers(3, 60))
    v = rng.normal(size=(n, 3))
    if seed % 4:
        v[:, 2] = np.abs(v[:, 2]) + 0.5 * (seed % 4)     # inside an open hemisphere
    v = unit(v).astype(np.float32)
    cones = []
    for w in (v, v[rng.permutation(n)], np.repeat(v, 2, 0), np.repeat(v[::-1], 3, 0)):
        out = np.empty(4)
        core._min_cone(np.ascontiguousarray(w), 0, len(w), out)
        cones.append(out)
    for out in cones[1:]:
        assert out.tobytes() == cones[0].tobytes()
    ang = np.arctan2(np.linalg.norm(np.cross(v.astype(np.float64), cones[0][:3]), axis=1), v.astype(np.float64) @ cones[0][:3])
    assert ang.max() <= cones[0][3]
    if cones[0][3] >= math.pi / 2:
        assert tuple(cones[0]) == (0.0, 0.0, 1.0, math.pi)


def fib_sphere(n):
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = i * math.pi * (3 - math.sqrt(5))
    s = np.sqrt(1 - z * z)
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)


def cone_boundary(a, th, k=64):
    """k unit vectors on the boundary of cone (a, th)."""
    a = a / np.linalg.norm(a)
    t = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
    t /= np.linalg.norm(t)
    b = np.cross(a, t)
    w = np.linspace(0, 2 * np.pi, k, endpoint=False)
    return np.cos(th) * a + np.sin(th) * (np.cos(w)[:, None] * t + np.sin(w)[:, None] * b)


@pytest.mark.parametrize("seed", range(12))
def test_cone_merge_contains_children_and_is_minimal(seed):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=3); a /= np.linalg.norm(a)
    b = rng.normal(size=3); b /= np.linalg.norm(b)
    if seed == 0:
        b = -a  # antipodal axes
    ta, tb = rng.random(2) * [1.2, 0.6]
    out = core._merge_cones(*a, ta, *b, tb)
    u, th = np.array(out[:3]), out[3]
    for ax, t in ((a, ta), (b, tb)):
        v = np.vstack([cone_boundary(ax, t), ax])
        ang = np.arctan2(np.linalg.norm(np.cross(v, u), axis=1), v @ u)
        assert ang.max() <= th + 1e-12
    # brute force over axes: the smallest cone containing both
    g = fib_sphere(200000)
    need = np.maximum(np.arccos(np.clip(g @ a, -1, 1)) + ta, np.arccos(np.clip(g @ b, -1, 1)) + tb)
    best = min(need.min(), np.pi)
    assert th <= best + 1e-9
    assert th >= best - 0.02  # grid resolution (~0.008 rad spacing)


def test_pack_cones_conservative_and_tight():
    rng = np.random.default_rng(2)
    M = 2000
    axis = rng.normal(size=(M, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    axis[:6] = np.eye(3).tolist() + (-np.eye(3)).tolist()
    half = rng.random(M) * np.pi
    half[:50] = 0.0
    half[50:60] = np.pi
    packed, dec, dhalf = pack_cones(axis, half)
    ax_g, half_g = glsl_decode(packed)
    for i in range(M):
        v = np.vstack([cone_boundary(axis[i], half[i], 32), axis[i]])
        for u, h in ((dec[i].astype(np.float64), float(dhalf[i])), (ax_g[i], half_g[i])):
            ang = np.arctan2(np.linalg.norm(np.cross(v, u), axis=1), v @ u)
            assert ang.max() <= h + 1e-12, (i, ang.max() - h)
    assert np.all((packed[50:60] >> 24) == 255)
    # widening is at most the axis quantisation error plus one alpha step
    widen = dhalf.astype(np.float64) - half
    axis_err = np.arctan2(np.linalg.norm(np.cross(axis, dec.astype(np.float64)), axis=1), np.sum(axis * dec, axis=1))
    ok = half < np.pi * 254 / 255
    assert np.all(widen[ok] <= axis_err[ok] + np.pi / 255 + 1e-5)


def test_config_check():
    for bad in (dict(bits=0), dict(bits=22), dict(tc=-1.0), dict(tn=1.5), dict(exact_cone_max=1)):
        with pytest.raises(ConfigError):
            BuildBshConfig(**bad).check()
    BuildBshConfig(tc=float("inf"), tn=-1.0).check()


# ----------------------------------------------------------------------------- whole builds
@pytest.mark.parametrize("kind", ["random", "random_bits4", "room", "wall_jitter", "room_pruned"])
def test_invariants(kind):
    if kind == "random":
        p, n, c = random_cloud(1500, seed=11, hemi=False)
        r = build_bsh(p, n, c, prune=False)
    elif kind == "random_bits4":  # voxels holding many points
        p, n, c = random_cloud(3000, seed=12, hemi=True)
        r = build_bsh(p, n, c, bits=4, prune=False)
        assert r["stats"]["n_multi_point_voxels"] > 0
    elif kind == "room":
        p, n, c = room_cloud(4000, seed=1)
        r = build_bsh(p, n, c, prune=False, exact_cone_max=4)
    elif kind == "wall_jitter":
        p, n, c = wall(50, 40, 0.02, noise=0.05, jitter=True)
        r = build_bsh(p, n, c, prune=False)
    else:
        p, n, c = room_cloud(4000, seed=2)
        r = build_bsh(p, n, c, tc=0.05, tn=0.9)
        assert r["stats"]["n_clusters"] > 0
    check_tree(r, p, n, c)


def test_leaves_are_voxels_with_averaged_points():
    p, n, c = random_cloud(4000, seed=4, hemi=True)
    bits = 3
    r = build_bsh(p, n, c, bits=bits, prune=False, emitters="none")   # leaves keep their colour
    code, q = morton_reference(p, bits)
    o = r["order"]
    # Morton order, ties in input order
    assert np.array_equal(o, np.lexsort((np.arange(len(p)), code)))
    leaf = np.flatnonzero(r["child"][:, 0] < 0)
    assert len(leaf) == len(np.unique(code))
    for i in leaf:
        idx = o[r["first"][i]:r["first"][i] + r["count"][i]]
        assert len(np.unique(code[idx])) == 1
        assert np.allclose(r["center"][i], p[idx].astype(np.float64).mean(0), atol=2e-7 * (1 + np.abs(p).max()))
        assert np.allclose(r["color"][i], c[idx].astype(np.float64).mean(0), rtol=1e-6)
        nm = n[idx].astype(np.float64).sum(0)
        assert np.allclose(r["normal"][i], nm / np.linalg.norm(nm), atol=1e-6)
    # leaves are sorted by voxel code, one each
    lcodes = code[o[r["first"][leaf]]]
    assert np.all(np.diff(lcodes.astype(np.float64)) > 0) or len(leaf) == 1


@pytest.mark.parametrize("jitter", [False, True])
def test_leaf_radius_from_spacing(jitter):
    """One-point leaves get radius d4/sqrt(2), d4 = 4th-nearest-leaf distance found in two
    Morton windows: an upper bound of the exact value (scipy k-d tree), equal to it for most
    points (on a grid, discs of radius s/sqrt(2) cover the plane without gaps)."""
    from scipy.spatial import cKDTree

    s = 0.05
    p, n, c = wall(40, 40, s, noise=0.1, jitter=jitter)
    r = build_bsh(p, n, c, prune=False)
    leaf = np.flatnonzero(r["child"][:, 0] < 0)
    assert len(leaf) == 1600 and np.all(r["count"][leaf] == 1)
    rad = r["radius"][leaf].astype(np.float64)
    cen = r["center"][leaf].astype(np.float64)
    d4 = cKDTree(cen).query(cen, 5)[0][:, 4]
    ratio = rad / (d4 / math.sqrt(2))
    assert np.all(ratio >= 1 - 1e-9)
    exact = ratio <= 1 + 1e-6  # float32 round-up of the radius: 2.4e-7
    assert np.mean(exact) > 0.85, np.mean(exact)
    assert np.max(ratio) < 3.0
    if not jitter:
        assert np.median(rad) == pytest.approx(s / math.sqrt(2), rel=1e-5)


def test_karras_tree_of_build_matches_reference():
    p, n, c = random_cloud(300, seed=9)
    r = build_bsh(p, n, c, bits=21, prune=False)
    code, _ = morton_reference(p, 21)
    lc = np.unique(code)
    ref = radix_reference(lc)
    # leaf index ranges of every inner node of the build
    leaf = r["child"][:, 0] < 0
    leaf_rank = np.full(len(leaf), -1)
    leaf_rank[leaf] = np.argsort(np.argsort(r["first"][leaf]))
    M = len(leaf)
    lo = np.zeros(M, dtype=np.int64)
    hi = np.zeros(M, dtype=np.int64)
    for i in range(M - 1, -1, -1):
        if leaf[i]:
            lo[i] = hi[i] = leaf_rank[i]
        else:
            lo[i] = lo[i + 1]
            hi[i] = hi[r["child"][i, 1]]
    got = {(int(lo[i]), int(hi[i])): ((int(lo[i + 1]), int(hi[i + 1])),
                                      (int(lo[r["child"][i, 1]]), int(hi[r["child"][i, 1]])))
           for i in range(M) if not leaf[i]}
    assert got == ref


# ----------------------------------------------------------------------------- pruning
def brute_prunable(C, Nn, idx, tc, tn, stat):
    mean = C[idx].mean(0)
    d = np.linalg.norm(C[idx] - mean, axis=1)
    s = Nn[idx].sum(0)
    nd = (Nn[idx] @ (s / np.linalg.norm(s))).mean() if np.linalg.norm(s) > 0 else 0.0
    cd = d.mean() if stat == "mean" else d.max()
    return cd < tc and nd > tn


def test_pruning_collapses_with_infinite_thresholds():
    p, n, c = random_cloud(2000, seed=6)
    r = build_bsh(p, n, c, tc=float("inf"), tn=-1.0)
    assert len(r["radius"]) == 1 and r["cluster"][0] == 1 and r["count"][0] == 2000
    check_tree(r, p, n, c)


def test_pruning_off_with_zero_tc_on_noisy_cloud():
    p, n, c = room_cloud(3000, seed=3)
    r = build_bsh(p, n, c, tc=0.0, tn=-1.0)
    assert r["stats"]["n_clusters"] == 0
    assert len(r["radius"]) == 2 * r["stats"]["n_voxels"] - 1


def test_uniform_flat_wall_prunes_to_few_clusters():
    p, n, c = wall(60, 60, 0.03, jitter=True)
    r = build_bsh(p, n, c)
    assert len(r["radius"]) <= 3
    assert r["stats"]["n_nodes_full"] == 2 * 3600 - 1
    check_tree(r, p, n, c)


@pytest.mark.parametrize("stat", ["mean", "max"])
def test_pruning_picks_topmost_subtrees_passing_the_test(stat):
    """Four walls of two orientations and four colours with small noise: every cluster passes
    the §5.1 test by brute force, and no inner node left in the tree does."""
    parts = []
    rng = np.random.default_rng(0)
    for k, (col, nrm) in enumerate((((0.2, 0.3, 0.4), (0, 0, 1)), ((0.8, 0.1, 0.1), (0, 0, 1)),
                                    ((0.2, 0.3, 0.4), (1, 0, 0)), ((0.5, 0.5, 0.5), (0, 1, 0)))):
        m = 800
        q = rng.random((m, 3)) * [1, 1, 0]
        if nrm == (1, 0, 0):
            q = q[:, [2, 0, 1]]
        if nrm == (0, 1, 0):
            q = q[:, [0, 2, 1]]
        q += [2.0 * k, 0, 0]
        nn = np.tile(nrm, (m, 1)) + rng.normal(0, 0.08, (m, 3))
        cc = np.array(col) + rng.normal(0, 0.006, (m, 3))
        parts.append((q, nn, cc))
    p = np.vstack([a for a, _, _ in parts]).astype(np.float32)
    n = unit(np.vstack([b for _, b, _ in parts]))
    c = np.abs(np.vstack([x for _, _, x in parts])).astype(np.float32)
    tc, tn = 0.01, 0.98
    r = build_bsh(p, n, c, tc=tc, tn=tn, prune_stat=stat)
    check_tree(r, p, n, c)
    C = c.astype(np.float64)
    Nn = n.astype(np.float64)
    o = r["order"]
    ncl = 0
    for i in range(len(r["radius"])):
        idx = o[r["first"][i]:r["first"][i] + r["count"][i]]
        if r["cluster"][i]:
            ncl += 1
            assert brute_prunable(C, Nn, idx, tc, tn, stat)
        elif r["child"][i, 0] >= 0:
            assert not brute_prunable(C, Nn, idx, tc, tn, stat)
    assert ncl == r["stats"]["n_clusters"] > 0
    assert r["stats"]["n_nodes"] < r["stats"]["n_nodes_full"]


# ----------------------------------------------------------------------------- extremes
def test_single_point():
    p = np.array([[1.0, 2.0, 3.0]], dtype=np.float32)
    n = unit([[0.0, 1.0, 0.0]])
    c = np.array([[1.0, 2.0, 3.0]], dtype=np.float32)
    r = build_bsh(p, n, c)
    assert len(r["radius"]) == 1 and r["child"][0, 0] == -1 and r["radius"][0] == 0.0
    assert np.array_equal(r["center"][0], p[0]) and np.array_equal(r["color"][0], c[0])
    check_tree(r, p, n, c)


def test_two_identical_points_and_all_identical():
    for N in (2, 500):
        p = np.tile(np.float32([0.3, -1.0, 7.0]), (N, 1))
        n = unit(np.tile([1.0, 1.0, 0.0], (N, 1)))
        c = np.random.default_rng(N).random((N, 3)).astype(np.float32)
        r = build_bsh(p, n, c, prune=False)
        assert len(r["radius"]) == 1 and r["count"][0] == N and r["radius"][0] == 0.0
        check_tree(r, p, n, c)


def test_coplanar_and_collinear():
    p, n, c = random_cloud(1000, seed=8)
    p[:, 1] = 0.25
    check_tree(build_bsh(p, n, c, prune=False), p, n, c)
    p[:, 2] = -3.0
    check_tree(build_bsh(p, n, c, prune=False), p, n, c)


@pytest.mark.parametrize("scale,offset", [(1e-3, 0.0), (1e4, 0.0), (1.0, 1e4), (1e-3, 1.0)])
def test_extreme_coordinate_ranges(scale, offset):
    p, n, c = room_cloud(2000, seed=5)
    p = (p.astype(np.float64) / 5.0 * scale + offset).astype(np.float32)
    r = build_bsh(p, n, c, prune=False)
    check_tree(r, p, n, c)
    assert r["stats"]["cube_side"] == pytest.approx(float(np.max(p.max(0).astype(np.float64) - p.min(0))), rel=1e-12)


def test_more_points_than_cells_along_an_axis():
    """2^21 + 100 000 points on a segment: Morton codes collide (several points a voxel)."""
    N = 2 ** 21 + 100_000
    x = np.linspace(0.0, 1.0, N, dtype=np.float64)
    p = np.zeros((N, 3), dtype=np.float32)
    p[:, 0] = x
    n = np.tile(np.float32([0, 1, 0]), (N, 1))
    c = np.tile(np.float32([0.5, 0.5, 0.5]), (N, 1))
    c[::3] = 0.7
    r = build_bsh(p, n, c, prune=False, emitters="none")   # the line's ends are isolated: keep them leaves
    st = r["stats"]
    assert st["n_voxels"] < N and st["n_multi_point_voxels"] > 0
    o, first, count, child = r["order"], r["first"], r["count"], r["child"]
    assert np.array_equal(np.sort(o), np.arange(N))
    leaf = np.flatnonzero(child[:, 0] < 0)
    # every point inside its leaf's sphere; leaf colours are the voxel means (vectorised)
    srt = leaf[np.argsort(first[leaf])]
    owner = np.repeat(srt, count[srt])
    P = p[o].astype(np.float64)
    d = np.linalg.norm(P - r["center"][owner].astype(np.float64), axis=1)
    assert np.all(d <= r["radius"][owner].astype(np.float64) * (1 + DIST_TOL))
    sums = np.add.reduceat(c[o].astype(np.float64), first[srt], axis=0)
    assert np.allclose(r["color"][srt], sums / count[srt][:, None], rtol=1e-6)
    # inner spheres contain their children; ranges add up
    ii = np.flatnonzero(child[:, 0] >= 0)
    cc = r["center"].astype(np.float64)
    rr = r["radius"].astype(np.float64)
    for k in (child[ii, 0], child[ii, 1]):
        assert np.all(np.linalg.norm(cc[ii] - cc[k], axis=1) + rr[k] <= rr[ii] * (1 + DIST_TOL))
    assert np.all(count[ii] == count[child[ii, 0]] + count[child[ii, 1]])


@pytest.mark.parametrize("what", ["nan_normal", "inf_normal", "zero_normal", "nan_point", "inf_colour"])
def test_bad_values_rejected(what):
    p, n, c = random_cloud(50, seed=1)
    if what == "nan_normal":
        n[3] = np.nan
    elif what == "inf_normal":
        n[3, 0] = np.inf
    elif what == "zero_normal":
        n[3] = 0
    elif what == "nan_point":
        p[7, 2] = np.nan
    else:
        c[1, 1] = np.inf
    with pytest.raises(InputError) as e:
        build_bsh(p, n, c, where="cloud.ply")
    msg = str(e.value)
    assert msg.startswith("cloud.ply: 1 points have") and "\n" not in msg


# ----------------------------------------------------------------------------- CLI, files
def write_ply(path, p, n, c):
    from plyfile import PlyData, PlyElement

    a = np.empty(len(p), dtype=[(k, "<f4") for k in ("x", "y", "z", "nx", "ny", "nz", "red", "green", "blue")])
    for i, k in enumerate("xyz"):
        a[k] = p[:, i]
        a["n" + k] = n[:, i]
    for i, k in enumerate(("red", "green", "blue")):
        a[k] = c[:, i]
    PlyData([PlyElement.describe(a, "vertex")], text=False, byte_order="<").write(str(path))


def test_cli_writes_valid_deterministic_file(tmp_path, cli_run):
    from pipeline.io import read_json, read_npz

    p, n, c = room_cloud(3000, seed=4)
    ply = tmp_path / "cloud.ply"
    write_ply(ply, p, n, c)
    outs = []
    for k in range(2):
        out = tmp_path / f"bsh{k}.npz"
        code, _, err = cli_run("build-bsh", ply, "--out", out, "--tc", "0.05", "--tn", "0.9",
                               *(["--preview", tmp_path / "bsh.png"] if k == 0 else []))
        assert code == 0, err
        outs.append(out.read_bytes())
    assert outs[0] == outs[1]  # byte-identical
    d = read_npz(tmp_path / "bsh0.npz", SCHEMA)
    assert d["nodes"].dtype.itemsize == 40
    nodes = d["nodes"].view(NODE_DTYPE)
    d["nodes"] = nodes
    check_tree(d, p, n, c)
    rep = read_json(tmp_path / "bsh0.json")
    assert rep["counts"]["n_nodes"] == len(nodes) and rep["counts"]["n_clusters"] == int(d["cluster"].sum())
    assert (tmp_path / "bsh.png").stat().st_size > 1000
    code, _, err = cli_run("build-bsh", ply, "--out", tmp_path / "x.npz", "--no-prune", "--bits", "10")
    assert code == 0 and len(read_npz(tmp_path / "x.npz", SCHEMA)["radius"]) == 2 * int(
        read_npz(tmp_path / "x.npz", SCHEMA)["n_voxels"]) - 1


def test_cli_rejects_bad_normals_and_options(tmp_path, cli_run):
    p, n, c = random_cloud(100, seed=2)
    n[5] = 0.0
    ply = tmp_path / "bad.ply"
    write_ply(ply, p, n, c)
    code, _, err = cli_run("build-bsh", ply, "--out", tmp_path / "b.npz")
    assert code == 1
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("pcrelight:")]
    assert len(lines) == 1 and str(ply) in lines[0] and "zero-length normals" in lines[0]
    assert not (tmp_path / "b.npz").exists()
    n[5] = np.nan
    write_ply(ply, p, n, c)
    code, _, err = cli_run("build-bsh", ply, "--out", tmp_path / "b.npz")
    assert code == 1 and "non-finite normals" in err
    code, _, err = cli_run("build-bsh", ply, "--out", tmp_path / "b.npz", "--bits", "30")
    assert code == 2 and "--bits" in err
    code, _, err = cli_run("build-bsh", ply, "--out", tmp_path / "b.npz", "--emitters", "all")
    assert code == 2 and "--emitters" in err
    for opt, bad in (("--isolated", "0.5"), ("--closed-share", "0"), ("--closed-contrast", "-1"), ("--emitter-size", "0")):
        code, _, err = cli_run("build-bsh", ply, "--out", tmp_path / "b.npz", opt, bad)
        assert code == 2 and opt in err and err.strip().count("\n") == 0, opt
    assert not (tmp_path / "b.npz").exists()


def test_tiny_ground_truth_scene(tiny_scene):
    """The invariants on the ground truth's `tiny` preset (its HDR cloud), with the default
    pruning (t_c = 0.01, t_n = 0.98) and without."""
    from pipeline.io import read_cloud

    cl = read_cloud(tiny_scene / "cloud_gt.ply")
    for prune in (True, False):
        r = build_bsh(cl.points, cl.normals, cl.colors, prune=prune)
        check_tree(r, cl.points, cl.normals, cl.colors)
        st = r["stats"]
        assert st["n_points"] == len(cl) and (st["n_clusters"] > 0) == prune


def test_node_record_matches_the_std430_struct():
    """struct Node { uint right; uint skip; float cx, cy, cz; float r, g, b; float radius; uint cone; }"""
    f = NODE_DTYPE.fields
    assert NODE_DTYPE.itemsize == 40
    assert [(k, f[k][1]) for k in NODE_DTYPE.names] == [("right", 0), ("skip", 4), ("center", 8), ("color", 20),
                                                       ("radius", 32), ("cone", 36)]
    p, n, c = random_cloud(300, seed=3)
    r = build_bsh(p, n, c)
    raw = np.frombuffer(r["nodes"].tobytes(), dtype="<u4").reshape(-1, 10)
    fl = raw.view("<f4")
    assert np.array_equal(raw[:, 0], np.where(r["child"][:, 1] >= 0, r["child"][:, 1], -1).astype(np.int64) & 0xFFFFFFFF)
    assert np.array_equal(fl[:, 2:5], r["center"]) and np.array_equal(fl[:, 5:8], r["color"])
    assert np.array_equal(fl[:, 8], r["radius"])


# ----------------------------------------------------------------------------- splat radii
def test_splat_radius_is_voxel_area_capped_by_the_sphere():
    """splat_radius = min(radius, sqrt(Σ r²)) over the voxel leaves holding the node's points (voxel radii
    from the unpruned tree of the same cloud, summed by brute force per point): a voxel leaf keeps its
    radius; inner nodes and pruned clusters are capped. On a filled (jittered-grid) wall every node of ≥ 16
    points still reaches all its points with its splat (the cap trims the bounding spheres' growth up the
    tree; nodes of a few points may be trimmed inside their extent, their area kept — the furnace test of
    test_relight.py checks that this leaves no gap); the cluster of two small patches 1.1 m apart (pruned:
    same colour, same normal) shrinks to the area of its voxels' splats."""
    def check(p, n, c):
        full = build_bsh(p, n, c, prune=False)
        vox = np.flatnonzero(full["child"][:, 0] < 0)
        share = np.zeros(len(p))                       # per input point: its voxel's r² / its voxel's points
        for v in vox:
            idx = full["order"][full["first"][v]:full["first"][v] + full["count"][v]]
            share[idx] = float(full["radius"][v]) ** 2 / len(idx)
        for r in (full, build_bsh(p, n, c)):
            s2 = np.array([share[r["order"][f:f + k]].sum() for f, k in zip(r["first"], r["count"])])
            want = np.minimum(r["radius"].astype(np.float64), np.sqrt(s2))
            assert r["splat_radius"].dtype == np.float32
            assert np.allclose(r["splat_radius"], want, rtol=1e-6, atol=0)
            assert np.all(r["splat_radius"] <= r["radius"])
            assert np.array_equal(r["splat_radius"][np.isin(r["first"], full["first"][vox]) & (r["count"] == 1)],
                                  r["radius"][np.isin(r["first"], full["first"][vox]) & (r["count"] == 1)])
        return full, r

    p, n, c = wall(40, 40, 0.05, jitter=True)
    full, _ = check(p, n, c)
    sp = p[full["order"]].astype(np.float64)
    for i in np.flatnonzero(full["count"] >= 16):
        f, k = full["first"][i], full["count"][i]
        far = np.max(np.linalg.norm(sp[f:f + k] - full["center"][i], axis=1))
        assert far <= full["splat_radius"][i], (i, far, full["splat_radius"][i], full["radius"][i])
    q, m, _ = wall(6, 6, 0.02, seed=1)
    pts = np.concatenate([q, q + np.float32([1.1, 0, 0])])
    _, r = check(pts, np.concatenate([m, m]), np.ones((len(pts), 3), np.float32))
    assert r["cluster"][0] == 1 and r["count"][0] == 72
    assert r["splat_radius"][0] < 0.25 * r["radius"][0], (r["splat_radius"][0], r["radius"][0])


def test_isolated_leaves_splat_their_share_of_area():
    """--isolated 2 (default): three points of a 4 cm lamp 0.3 m in front of a 5 cm grid wall have their
    4th-nearest leaf on the wall (spacing ≈ 0.3 m, > 2 × the 0.05 m of their 16 nearest leaves): their
    spacing becomes that median / sqrt(2), so the disc is the point's share of area (0.05² / 2 … on a
    grid πr² = π s² / 4); no wall leaf changes (the Morton bound overestimates by at most sqrt(2));
    --isolated 0 changes nothing."""
    p, n, c = wall(40, 40, 0.05)
    lamp = np.array([[1.0, 1.0, 0.30], [1.03, 1.0, 0.31], [1.0, 1.03, 0.32]])
    pts = np.vstack([p, lamp])
    nrm = np.vstack([n, np.tile([0.0, 0.0, 1.0], (3, 1))])
    col = np.vstack([c, np.full((3, 3), 50.0)])
    off = build_bsh(pts, nrm, col, prune=False, isolated=0.0)
    on = build_bsh(pts, nrm, col, prune=False)
    assert off["stats"]["n_isolated"] == 0 and on["stats"]["n_isolated"] == 3

    def leaf_r(r, idx):
        leaf = np.flatnonzero(r["child"][:, 0] < 0)
        pos = r["center"][leaf].astype(np.float64)
        return r["radius"][leaf[[int(np.argmin(np.linalg.norm(pos - pts[i], axis=1))) for i in idx]]].astype(np.float64)

    lamp_idx = [1600, 1601, 1602]
    assert np.all(leaf_r(off, lamp_idx) > 0.2)
    # radius = max(own extent (0), spacing / sqrt(2)), spacing = the median / sqrt(2) of wall spacings in
    # [0.05, 0.05·sqrt(2)] (exact 4-NN distance … its Morton upper bound): radius in [0.025, 0.0354]
    r_lamp = leaf_r(on, lamp_idx)
    assert np.all(r_lamp >= 0.05 / 2 * (1 - 1e-6)) and np.all(r_lamp <= 0.05 * math.sqrt(2) / 2 * (1 + 1e-6))
    np.testing.assert_array_equal(leaf_r(on, np.arange(1600)), leaf_r(off, np.arange(1600)))


def test_closure_share_of_a_sphere_a_patch_a_corner_and_a_mix():
    """closure_share (the splat-area factor of a node, c + (1 − c)/8 with c = |Σ w n| / Σ w): points on a
    sphere (a lamp, normals all round) get ≈ 1/8; a flat patch keeps ≥ 0.99 whatever its normals' noise;
    a room corner (floor + two walls, c = 1/√3) 1/√3 + (1 − 1/√3)/8; a node of a patch and a lamp of equal
    weight is half flat; weights count (a patch of weight 3 against a lamp of weight 1); closed_share 1
    turns it off."""
    from pipeline.bsh.builder import closure_share

    rng = np.random.default_rng(0)
    d = rng.normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    w = np.ones(2000)
    one = (np.array([0]), np.array([2000]))
    c = np.linalg.norm(d.sum(0)) / 2000
    f = closure_share(d, w, *one, 0.125)
    assert c < 0.05 and f[0] == pytest.approx(c + (1 - c) * 0.125)
    assert closure_share(d, w, *one, 1.0)[0] == pytest.approx(1.0)
    nn = np.tile([0.0, 0.0, 1.0], (2000, 1)) + rng.normal(0, 0.05, (2000, 3))
    nn /= np.linalg.norm(nn, axis=1, keepdims=True)
    assert closure_share(nn, w, *one, 0.125)[0] >= 0.99
    cn = np.repeat(np.eye(3), 2000, axis=0)
    assert closure_share(cn, np.ones(6000), np.array([0]), np.array([6000]), 0.125)[0] == pytest.approx(
        1 / math.sqrt(3) + (1 - 1 / math.sqrt(3)) / 8)
    up = np.tile([0.0, 0.0, 1.0], (2000, 1))
    mixed = closure_share(np.concatenate([up, d]), np.ones(4000), np.array([0, 2000]), np.array([4000, 2000]), 0.125)
    cm = np.linalg.norm(up.sum(0) + d.sum(0)) / 4000
    assert 0.45 <= cm <= 0.55 and mixed[0] == pytest.approx(cm + (1 - cm) / 8) and mixed[1] == pytest.approx(f[0])
    heavy = closure_share(np.concatenate([up, d]), np.concatenate([np.full(2000, 3.0), w]), np.array([0]),
                          np.array([4000]), 0.125)
    ch = np.linalg.norm(3 * up.sum(0) + d.sum(0)) / 8000
    assert ch >= 0.7 and heavy[0] == pytest.approx(ch + (1 - ch) / 8)


def ball_before_wall():
    """A 5 cm grid wall (colours c) and a 0.12 m sphere of 200 random points with outward normals 0.73 m in
    front of it, inside one Morton cell of its own: (points, normals, wall colours c, centre)."""
    p, n, c = wall(40, 40, 0.05)
    rng = np.random.default_rng(1)
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    centre = np.array([0.73, 0.73, 0.73])
    return np.vstack([p, centre + 0.12 * d]), np.vstack([n, d]), c, centre


def test_build_bsh_shrinks_the_splat_of_a_closed_lamp_only():
    """A 0.12 m sphere of 200 points (a lamp) 0.73 m in front of a 5 cm grid wall (inside one Morton cell of its own): the node holding exactly the
    lamp splats with about a quarter of its surface area (closed_share 1/8 of its leaves' splat area, which
    is ≈ 2× its area) instead of its bounding sphere; with closed_share 1 it is the bounding sphere (> 5× the
    lamp's cross-section); every wall node keeps its splat radius."""
    pts, nrm, c, centre = ball_before_wall()
    col = np.vstack([c, np.full((200, 3), 50.0)])
    on, off = build_bsh(pts, nrm, col), build_bsh(pts, nrm, col, closed_share=1.0)
    assert on["stats"]["n_closed"] > 0 and off["stats"]["n_closed"] == 0
    lamp = np.flatnonzero(on["count"] == 200)
    lamp = lamp[np.linalg.norm(on["center"][lamp] - centre, axis=1) < 0.05]
    assert len(lamp) == 1
    cross = math.pi * 0.12 ** 2
    assert math.pi * off["splat_radius"][lamp[0]] ** 2 > 5 * cross
    assert 0.7 * cross <= math.pi * on["splat_radius"][lamp[0]] ** 2 <= 1.6 * cross
    inv = np.empty(len(pts), np.int64)
    inv[on["order"]] = np.arange(len(pts))
    first_lamp = inv[1600:].min()
    wall_only = (on["first"] + on["count"] <= first_lamp) | (on["first"] > inv[1600:].max())
    np.testing.assert_array_equal(on["splat_radius"][wall_only], off["splat_radius"][wall_only])


def test_isolated_leaves_become_emitters_and_leave_the_node_colours():
    """--emitters isolated (default): the three isolated points of a 4 cm lamp in front of a grid wall
    become emitters (E, 12): centre = the point, disc radius = its leaf's (its share of area), unit normal,
    radiance; their leaves splat nothing (radius 0) and every node's colour counts them black (the root's
    colour × its count = the wall's colour sum, so the walk and the emitter gather do not count them
    twice); --emitters none keeps them in the tree as before."""
    p, n, c = wall(40, 40, 0.05)
    lamp = np.array([[1.0, 1.0, 0.30], [1.03, 1.0, 0.31], [1.0, 1.03, 0.32]])
    pts = np.vstack([p, lamp])
    nrm = np.vstack([n, np.tile([0.0, 0.0, 1.0], (3, 1))])
    col = np.vstack([c, np.full((3, 3), 50.0)])
    on, off = build_bsh(pts, nrm, col, prune=False), build_bsh(pts, nrm, col, prune=False, emitters="none")
    em = on["emitters"]
    assert em.shape == (3, 12) and off["emitters"].shape == (0, 12) and on["stats"]["n_emitters"] == 3
    order = np.argsort(em[:, 0] + 10 * em[:, 1])
    np.testing.assert_allclose(em[order, :3], lamp[[0, 1, 2]][np.argsort(lamp[:, 0] + 10 * lamp[:, 1])], atol=1e-6)
    np.testing.assert_allclose(em[:, 4:7], np.tile([0.0, 0.0, 1.0], (3, 1)), atol=1e-6)
    np.testing.assert_array_equal(em[:, 8:11], 50.0)
    leaf = np.flatnonzero(on["child"][:, 0] < 0)
    lamp_leaf = leaf[[int(np.argmin(np.linalg.norm(on["center"][leaf] - q, axis=1))) for q in lamp]]
    np.testing.assert_allclose(np.sort(em[:, 3]), np.sort(off["radius"][lamp_leaf]), rtol=1e-6)
    assert np.all(on["splat_radius"][lamp_leaf] == 0) and np.all(off["splat_radius"][lamp_leaf] > 0)
    np.testing.assert_allclose(on["color"][0] * on["count"][0], c.astype(np.float64).sum(0), rtol=1e-5)
    np.testing.assert_allclose(off["color"][0] * off["count"][0], col.astype(np.float64).sum(0), rtol=1e-5)
    wall_leaf = np.setdiff1d(leaf, lamp_leaf)
    np.testing.assert_array_equal(on["splat_radius"][wall_leaf], off["splat_radius"][wall_leaf])
    np.testing.assert_array_equal(on["color"][wall_leaf], off["color"][wall_leaf])


def test_compact_bright_finds_small_bright_objects_only():
    """compact_bright: on a wall (0.05 m grid, typical splat radius 0.035 m), an 8-point 4 cm lamp 0.3 m in front
    (its points 2–3 cm apart: not isolated) is a compact object; a bright 1 m patch of the wall (a sun patch)
    and a dim lamp are not; the sun's disc of radius 0.17 m (4.8 splat radii) is not at the default size 2.
    Flat share: the lamp's |Σ n| / n, the disc's 1."""
    from pipeline.bsh.builder import LEAF_SPLAT_SCALE as SPLAT_SCALE, compact_bright

    p, _, _ = wall(40, 40, 0.05)
    rng = np.random.default_rng(1)
    d = rng.normal(size=(8, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    lamp = np.array([0.5, 0.5, 0.3]) + 0.04 * d
    sun = np.column_stack([1.5 + 0.17 * np.cos(np.arange(30) * 2.4) * np.sqrt(np.arange(30) / 30),
                           1.5 + 0.17 * np.sin(np.arange(30) * 2.4) * np.sqrt(np.arange(30) / 30), np.full(30, 1.0)])
    cen = np.vstack([p, lamp, sun, lamp + [1.0, 0.0, 0.0]]).astype(np.float64)
    lum = np.full(len(cen), 0.5)
    patch = (cen[:, 0] > 1.0) & (cen[:, 0] < 2.0) & (cen[:, 1] > 0.2) & (cen[:, 1] < 1.2) & (cen[:, 2] == 0)
    lum[patch] = 100.0
    lamp_i = np.arange(len(p), len(p) + 8)
    sun_i = np.arange(len(p) + 8, len(p) + 38)
    dim_i = np.arange(len(p) + 38, len(p) + 46)
    lum[lamp_i] = 5000.0
    lum[sun_i] = 1e5
    lum[dim_i] = 1.0
    spacing = np.full(len(cen), 0.05)
    nsum = np.tile([0.0, 0.0, 1.0], (len(cen), 1))             # the wall and the sun's disc face +z
    nsum[lamp_i] = d
    got, flat, area = compact_bright(cen, spacing, lum, 30 * 0.5, 2.0, nsum, np.ones(len(cen)))
    assert got[lamp_i].all() and got.sum() == 8
    assert not got[sun_i].any() and not got[patch].any() and not got[dim_i].any()
    # the lamp's points and normals fit its sphere: each point a share of 4π R², closed (flat share 0); the
    # disc's parallel normals fit none: flat share |Σ n| / n = 1, no fitted area
    np.testing.assert_allclose(area[lamp_i], 4 * np.pi * 0.04 ** 2 / 8, rtol=1e-9)
    assert np.all(flat[lamp_i] == 0) and np.all(area[sun_i] == 0) and np.all(area[:len(p)] == 0)
    assert np.allclose(flat[sun_i], 1.0) and np.all(flat[dim_i] == 0)
    # normals that do not point from a common centre fit no sphere: the lamp keeps its flat share |Σ n| / n
    e = rng.normal(size=(8, 3))
    nsum[lamp_i] = e / np.linalg.norm(e, axis=1, keepdims=True)
    _, flat2, area2 = compact_bright(cen, spacing, lum, 30 * 0.5, 2.0, nsum, np.ones(len(cen)))
    assert np.all(area2[lamp_i] == 0)
    np.testing.assert_allclose(flat2[lamp_i], np.linalg.norm(nsum[lamp_i].sum(0)) / 8)
    big, _, _ = compact_bright(cen, spacing, lum, 30 * 0.5, 0.17 / (0.05 * SPLAT_SCALE) + 0.1)
    assert big[sun_i].all()
    assert not compact_bright(cen, spacing, lum, 1e6, 2.0)[0].any()


def test_a_lamp_of_several_points_becomes_emitters_of_its_share_of_area():
    """--emitters compact (default): an 8-point lamp (4 cm, 5000 × the wall) 0.3 m in front of a 0.05 m grid
    wall — not isolated, its points 2–3 cm apart — becomes 8 emitters whose discs hold its sphere's area
    4π R² (fitted to its points and normals; float32) and whose leaves splat nothing; with --emitters isolated
    it stays splatted, as before. Its normals scrambled (no sphere fits), the discs are the leaves' splat
    radius / sqrt(2) (a splat disc holds about twice a point's share of area)."""
    p, n, c = wall(40, 40, 0.05)
    rng = np.random.default_rng(1)
    d = rng.normal(size=(8, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    lamp = np.array([0.5, 0.5, 0.3]) + 0.04 * d
    pts, nrm = np.vstack([p, lamp]), np.vstack([n, d])
    col = np.vstack([c, np.full((8, 3), 5000.0)])
    on = build_bsh(pts, nrm, col, prune=False)
    off = build_bsh(pts, nrm, col, prune=False, emitters="isolated")
    assert on["stats"]["n_isolated"] == 0 and len(off["emitters"]) == 0
    em = on["emitters"]
    assert len(em) == 8 and on["stats"]["n_compact"] == 8
    leaf = np.flatnonzero(on["child"][:, 0] < 0)
    lamp_leaf = leaf[[int(np.argmin(np.linalg.norm(on["center"][leaf] - q, axis=1))) for q in lamp]]
    assert on["stats"]["n_sphere_fit"] == 8 and np.all(em[:, 7] == 0)
    np.testing.assert_allclose(em[:, 3], math.sqrt(4 * 0.04 ** 2 / 8), rtol=1e-5)
    assert np.all(on["splat_radius"][lamp_leaf] == 0) and np.all(off["splat_radius"][lamp_leaf] > 0)
    np.testing.assert_allclose(on["color"][0] * on["count"][0], c.astype(np.float64).sum(0), rtol=1e-5)
    e = rng.normal(size=(8, 3))
    scr = build_bsh(pts, np.vstack([n, e / np.linalg.norm(e, axis=1, keepdims=True)]), col, prune=False)
    assert scr["stats"]["n_sphere_fit"] == 0 and len(scr["emitters"]) == 8
    np.testing.assert_allclose(np.sort(scr["emitters"][:, 3]), np.sort(off["radius"][lamp_leaf]) / math.sqrt(2),
                               rtol=1e-6)


@pytest.mark.parametrize("grid", [0.15, 0.05])
def test_a_one_point_lamp_like_fitted_ones_takes_their_area(grid):
    """Two lamps of one radiance (4 cm spheres, 5000 × the wall) in front of a grid wall, one sampled by 6 points
    (its sphere fits: 4π R²), the other by one (nothing to fit): on a 0.15 m grid (a point's share ~0.018 m²: the
    sphere's 0.020 m² expects ~1 point) the one-point lamp is taken for the same fixture and gets the fitted one's
    area; on a 0.05 m grid (it would expect ~10 points: P(N ≤ 1) < 1 %) it is something smaller and keeps its own
    share of area. A one-point lamp of another colour always keeps its own."""
    p, n, c = wall(int(2.0 / grid), int(2.0 / grid), grid)
    rng = np.random.default_rng(3)
    d = rng.normal(size=(6, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    one = np.array([[0.0, 0.6, 0.8]])
    pts = np.vstack([p, [0.5, 0.5, 0.3] + 0.04 * d, [1.5, 1.5, 0.3] + 0.04 * one, [1.0, 0.3, 0.3] + 0.04 * one])
    nrm = np.vstack([n, d, one, one])
    col = np.vstack([c, np.full((7, 3), 5000.0), [[100.0, 5000.0, 100.0]]])
    r = build_bsh(pts, nrm, col, prune=False)
    em = r["emitters"]
    area = math.pi * em[:, 3].astype(np.float64) ** 2
    lamp = np.linalg.norm(em[:, :3] - [0.5, 0.5, 0.3], axis=1) < 0.1
    alike = np.linalg.norm(em[:, :3] - [1.5, 1.5, 0.3], axis=1) < 0.1
    other = np.linalg.norm(em[:, :3] - [1.0, 0.3, 0.3], axis=1) < 0.1
    assert lamp.sum() == 6 and alike.sum() == 1 and other.sum() == 1
    assert area[lamp].sum() == pytest.approx(4 * math.pi * 0.04 ** 2, rel=1e-5)
    if grid > 0.1:
        assert r["stats"]["n_sphere_fit"] == 7
        assert area[alike].sum() == pytest.approx(4 * math.pi * 0.04 ** 2, rel=1e-5)
    else:
        assert r["stats"]["n_sphere_fit"] == 6 and area[alike].sum() < 0.5 * 4 * math.pi * 0.04 ** 2
    # the other colour: its own share of area (~0.88 × the sphere's on the sparse grid, 0.1 × on the dense one)
    assert area[other].sum() != pytest.approx(4 * math.pi * 0.04 ** 2, rel=0.05) and np.all(em[:, 7] == 0)


def test_emitters_beyond_the_cap_stay_splatted(monkeypatch):
    """More isolated leaves than builder.MAX_EMITTERS (Eq. 9 loops over all of them per receiver): the
    brightest are emitters, the others stay ordinary leaves (their colour and splat), counted in the stats."""
    import pipeline.bsh.builder as bb

    p, n, c = wall(40, 40, 0.05)
    lamp = np.array([[1.0, 1.0, 0.30], [1.03, 1.0, 0.31], [1.0, 1.03, 0.32]])
    pts = np.vstack([p, lamp])
    nrm = np.vstack([n, np.tile([0.0, 0.0, 1.0], (3, 1))])
    col = np.vstack([c, np.array([[50.0] * 3, [80.0] * 3, [20.0] * 3])])
    monkeypatch.setattr(bb, "MAX_EMITTERS", 2)
    r = bb.build_bsh(pts, nrm, col, prune=False)
    assert r["stats"]["n_emitter_candidates"] == 3 and len(r["emitters"]) == 2
    assert sorted(r["emitters"][:, 8].tolist()) == [50.0, 80.0]
    leaf = np.flatnonzero(r["child"][:, 0] < 0)
    dim = leaf[int(np.argmin(np.linalg.norm(r["center"][leaf] - lamp[2], axis=1)))]
    assert r["splat_radius"][dim] > 0 and r["color"][dim][0] == pytest.approx(20.0)


def test_a_dark_closed_node_keeps_its_splat():
    """--closed-contrast 30 (default): the same 0.12 m sphere of 200 points as the lamp above, but as dark
    as the wall (a roof beam's knot: an occluder, not a source) keeps its splat — shrunk, such nodes opened
    gaps the sun shone through; with --closed-contrast 0 it shrinks like the lamp."""
    pts, nrm, c, centre = ball_before_wall()
    col = np.vstack([c, np.tile(c[0], (200, 1))])
    dflt, every, off = (build_bsh(pts, nrm, col, **kw) for kw in ({}, {"closed_contrast": 0.0}, {"closed_share": 1.0}))
    ball = np.flatnonzero((dflt["count"] == 200) & (np.linalg.norm(dflt["center"] - centre, axis=1) < 0.05))
    assert len(ball) == 1 and dflt["stats"]["n_closed"] == 0
    assert dflt["splat_radius"][ball[0]] == off["splat_radius"][ball[0]]
    assert every["splat_radius"][ball[0]] < 0.6 * off["splat_radius"][ball[0]]


# ----------------------------------------------------------------------------- fast paths = their references
def _leaves_of(p, bits):
    """Leaf centres (float32 means, as float64), sorted leaf codes, cube of a cloud (build_bsh's steps 1-3)."""
    from pipeline.bsh.builder import cube_box

    p = np.asarray(p, np.float32)
    lo, side = cube_box(p)
    codes = core.morton_codes(p, lo, float(2 ** bits) / side, bits)
    order, sc = core.radix_argsort(codes, 3 * bits)
    first = np.flatnonzero(np.r_[True, sc[1:] != sc[:-1]])
    cnt = np.diff(np.r_[first, len(p)])
    cen = (np.add.reduceat(p[order].astype(np.float64), first, axis=0) / cnt[:, None]).astype(np.float32)
    return cen.astype(np.float64), sc[first], lo, side


@pytest.mark.parametrize("kind", ["uniform", "skewed", "plane_lamps", "grid", "tiny", "coarse"])
def test_isolated_spacing_grid_equals_the_kd_tree_reference(kind):
    """bsh_core.shrink_isolated_leaves (a grid of the leaves' Morton prefixes; 13 s → ~1 s at 3 M points) returns
    exactly splats.shrink_isolated (a k-d tree's 16 nearest): dense and sparse parts, lamps above a
    plane, a far outlier, a jittered grid, fewer leaves than k, coarse voxels, ratios 1, 1.2 and 2."""
    from pipeline.bsh.builder import leaf_spacing
    from pipeline.expansion.splats import shrink_isolated

    rng = np.random.default_rng(3)
    bits = 21
    if kind == "uniform":
        p = rng.random((20000, 3))
    elif kind == "skewed":
        p = rng.random((20000, 3)) ** 4
    elif kind == "plane_lamps":
        p = np.r_[np.c_[rng.random((20000, 2)) * [8, 4], np.zeros(20000)], rng.random((30, 3)) * [8, 4, 3],
                  [[100.0, 100.0, 100.0]]]
    elif kind == "grid":
        g = np.stack(np.meshgrid(np.arange(30), np.arange(30), np.arange(3)), -1).reshape(-1, 3) * 0.1
        p = g + rng.normal(0, 1e-4, g.shape)
    elif kind == "tiny":
        p = rng.random((12, 3))
    else:
        p, bits = rng.random((20000, 3)), 5
    cen, codes, lo, side = _leaves_of(p, bits)
    sp = leaf_spacing(cen, lo, side)
    for ratio, k in ((2.0, 16), (1.0, 16), (1.2, 5)):
        want, n_want = shrink_isolated(cen, sp, ratio, k)
        got, n_got = core.shrink_isolated_leaves(cen, codes, sp, ratio, k, bits, lo, side)
        assert n_got == n_want and got.tobytes() == want.tobytes(), (kind, ratio, k)
    assert core.shrink_isolated_leaves(cen, codes, sp, 0.0, 16, bits, lo, side)[1] == 0


def test_range_sums_and_closure_share_match_their_numpy_forms():
    """The numba prefix-sum kernels of the pack step are bit-identical to the numpy formulas they replaced
    (cumsum, differences at the node ranges, |Σ w n| / Σ w): the BSH stays byte-identical."""
    from pipeline.bsh.builder import closure_share, node_sums

    rng = np.random.default_rng(5)
    n = 50000
    nrm = unit(rng.normal(size=(n, 3)))
    w = rng.random(n) * 1e-3
    w[::7] = 0.0
    first = np.sort(rng.integers(0, n, 8000))
    count = np.minimum(rng.integers(1, 3000, 8000), n - first)

    def sums(v):
        v = np.asarray(v, np.float64)
        cs = np.concatenate([np.zeros((1,) + v.shape[1:]), np.cumsum(v, axis=0)])
        return cs[first + count] - cs[first]

    col = rng.random((n, 3)).astype(np.float32)
    col[3] = -0.0
    for v in (col, rng.random(n) < 0.3, rng.random(n)):
        got = node_sums(v, first, count)
        assert got.shape == sums(v).shape and got.tobytes() == sums(v).tobytes()
    for share in (0.125, 1.0):
        S = sums(np.concatenate([w[:, None], nrm.astype(np.float64) * w[:, None]], 1))
        c = np.clip(np.linalg.norm(S[:, 1:], axis=1) / np.maximum(S[:, 0], 1e-300), 0.0, 1.0)
        assert closure_share(nrm, w, first, count, share).tobytes() == (c + (1.0 - c) * share).tobytes()
    lr = rng.random(500) * 0.01
    lc = rng.integers(1, 5, 500)
    assert core.point_share(lr, lc).tobytes() == np.concatenate([[0.0], np.cumsum(np.repeat(lr ** 2 / lc, lc))]).tobytes()


def test_write_bsh_holds_the_arrays_of_write_npz(tmp_path):
    """build-bsh's writer (deflate level 1, float members stored) gives numpy.load the same arrays, byte for
    byte, as io.write_npz, and the same file twice."""
    from pipeline.bsh.build_bsh import STORED_KEYS, write_bsh
    from pipeline.io import read_npz, write_npz

    p, n, c = room_cloud(3000, seed=6)
    r = build_bsh(p, n, c)
    r.pop("stats")
    write_npz(tmp_path / "a.npz", SCHEMA, **r)
    write_bsh(tmp_path / "b.npz", r)
    write_bsh(tmp_path / "c.npz", r)
    assert (tmp_path / "b.npz").read_bytes() == (tmp_path / "c.npz").read_bytes()
    a, b = read_npz(tmp_path / "a.npz", SCHEMA), read_npz(tmp_path / "b.npz", SCHEMA)
    assert sorted(a) == sorted(b)
    for k in a:
        assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape and a[k].tobytes() == b[k].tobytes(), k
    import zipfile

    with zipfile.ZipFile(tmp_path / "b.npz") as zf:
        stored = {i.filename[:-4] for i in zf.infolist() if i.compress_type == zipfile.ZIP_STORED}
    assert stored == STORED_KEYS & set(r)


def test_write_bsh_threaded_zip_is_zipfiles_bytes(tmp_path, monkeypatch):
    """write_bsh lays the zip out itself (members deflated by a thread pool): the file is byte for byte the
    one zipfile writes (the writer it replaced, kept as the ZIP64 fallback), zipfile's CRC check passes, and
    a file that would pass ZIP_LIMIT goes through zipfile."""
    import zipfile

    from pipeline.bsh import build_bsh as bb

    p, n, c = room_cloud(3000, seed=7)
    r = build_bsh(p, n, c)
    r.pop("stats")
    bb.write_bsh(tmp_path / "a.npz", r)
    bb.write_bsh_zipfile(tmp_path / "z.npz", {**{k: np.asarray(v) for k, v in r.items()},
                                             "schema": np.asarray(SCHEMA)})
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "z.npz").read_bytes()
    with zipfile.ZipFile(tmp_path / "a.npz") as zf:
        assert zf.testzip() is None
    monkeypatch.setattr(bb, "ZIP_LIMIT", 1)
    monkeypatch.setattr(bb, "_deflate_member", None)  # the fallback must not use the threaded path
    bb.write_bsh(tmp_path / "b.npz", r)
    assert (tmp_path / "b.npz").read_bytes() == (tmp_path / "a.npz").read_bytes()


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 17, 40, 300])
def test_leaf_spacing_is_the_4th_nearest_among_both_windows(n):
    """leaf_spacing (nearest-in-order candidates first, the second window skipping leaves of the first) is the
    4th smallest distance over the distinct leaves of the two ±16 Morton windows (the farthest found when
    fewer than 4; 0 alone): brute force over the definition."""
    rng = np.random.default_rng(n)
    cen = rng.random((n, 3))
    perm2 = rng.permutation(n)
    pos2 = np.argsort(perm2)
    got = core.leaf_spacing(cen, perm2, 16)
    for i in range(n):
        cand = {j for j in range(max(0, i - 16), min(n, i + 17)) if j != i}
        cand |= {int(perm2[q]) for q in range(max(0, pos2[i] - 16), min(n, pos2[i] + 17)) if perm2[q] != i}
        d = sorted(float(np.sum((cen[j] - cen[i]) ** 2)) for j in cand)
        want = math.sqrt(d[min(3, len(d) - 1)]) if d else 0.0
        assert got[i] == want, (n, i)


def test_a_box_room_at_round_coordinates_keeps_its_tree_when_scaled():
    """Issue 45 §2: a 16 × 5 × 12 m box room whose ceiling (y = 5 in a 16 m cube: exactly cell 655 360 at 21
    bits) lay on a major Morton boundary; × 10⁻³ in float32 it rounded to 655 359.97 and crossed it, so the tree
    regrouped round the ceiling (the lamp room's image 59 % off with --emitters none). With the grid half a cell
    off the corner (builder.grid_origin) the scaled room has the same point order and the same node counts."""
    rng = np.random.default_rng(7)
    gx, gz = np.arange(0.0, 16.01, 0.5), np.arange(0.25, 12.0, 0.5)                  # x spans the cube's 16 m
    ceiling = np.c_[gx.repeat(gz.size), np.full(gx.size * gz.size, 5.0), np.tile(gz, gx.size)]
    walls = [ceiling, ceiling * [1, 0, 1], rng.uniform([0, 0.5, 0], [16, 4.9, 12], (600, 3))]   # + floor, clutter
    p = np.concatenate(walls)
    n = np.tile([0.0, 1.0, 0.0], (len(p), 1))
    c = rng.uniform(0.1, 1.0, (len(p), 3))
    a = build_bsh(p.astype(np.float32), n, c, emitters="none")
    b = build_bsh((p * 1e-3).astype(np.float32), n, c, emitters="none")
    assert np.array_equal(a["order"], b["order"])
    assert len(a["radius"]) == len(b["radius"])


def test_a_cloud_too_large_for_the_memory_is_refused_in_one_line(tmp_path, cli_run, monkeypatch):
    """Issue 46 (Table 3's never-fails-for-memory rule): build-bsh reads the point count from the cloud's header
    and refuses, before reading the points, a cloud whose build needs more than the free memory — one line naming
    what it needs and what is free, exit 1, nothing written; with enough memory the same file builds."""
    import pipeline.bsh.build_bsh as bb
    from pipeline import io

    p, n, c = random_cloud(5000, seed=2)
    io.write_cloud(tmp_path / "c.ply", io.Cloud(p, n, c))
    need = bb.memory_needed(5000)
    monkeypatch.setattr(bb, "available_memory", lambda: need - 1)
    code, _, err = cli_run("build-bsh", tmp_path / "c.ply", "--out", tmp_path / "b.npz", "-q")
    lines = [ln for ln in err.strip().splitlines() if ln]
    assert code == 1 and len(lines) == 1, err
    assert lines[0].startswith(f"pcrelight: {tmp_path / 'c.ply'}: 5000 points need about") and "GiB is free" in lines[0]
    assert not (tmp_path / "b.npz").exists() and not (tmp_path / "b.json").exists()
    monkeypatch.setattr(bb, "available_memory", lambda: need)
    assert cli_run("build-bsh", tmp_path / "c.ply", "--out", tmp_path / "b.npz", "-q")[0] == 0
