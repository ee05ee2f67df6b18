"""Mipmapped / Hybrid PBGI cut finding (pipeline/gather/cut.py): Z-order round trip, the cone mip-map
contains its normals and positions, the GPU traversal's pair counts equal the CPU simulation's, the cut
equals the classic per-pixel walk's (independent per-pixel depth-first reference), chunking under a tiny
transform-feedback budget changes nothing."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipeline.bsh.format import NODE_DTYPE
from pipeline.gather import GATHERERS, ClassicGatherer, GatherParams, Receivers
from pipeline.gather import cut as pm

LEAF = 0xFFFFFFFF


# ------------------------------------------------------------------------------------------ fixtures
def build_tiny_bsh(P: np.ndarray, N: np.ndarray, C: np.ndarray, leaf_radius: float) -> np.ndarray:
    """A small bounding-sphere hierarchy in the bsh.npz node layout, built independently of build-bsh:
    median split on the longest axis, one point a leaf, depth-first order, spheres containing their
    points' leaf spheres, conservative RGBA8 normal cones (decoded cone ⊇ true normals)."""
    recs: list = []

    def cone_code(normals: np.ndarray) -> int:
        a = normals.sum(0)
        a = a / np.linalg.norm(a) if np.linalg.norm(a) > 1e-9 else np.array([0.0, 0.0, 1.0])
        rgb = np.clip(np.round((a + 1) / 2 * 255), 0, 255).astype(int)
        dec = rgb / 255 * 2 - 1
        dec = dec / np.linalg.norm(dec)
        half = np.max(np.arccos(np.clip(normals @ dec, -1, 1))) + 1e-6
        A = int(np.ceil(half / np.pi * 255))
        A = 255 if A >= 255 else A
        return int(rgb[0] | (rgb[1] << 8) | (rgb[2] << 16) | (A << 24))

    def rec(idx: np.ndarray) -> int:
        i = len(recs)
        recs.append(None)
        pts = P[idx]
        if len(idx) == 1:
            right, center, radius = LEAF, pts[0], leaf_radius
        else:
            ax = int(np.argmax(pts.max(0) - pts.min(0)))
            order = idx[np.argsort(pts[:, ax], kind="stable")]
            h = len(order) // 2
            rec(order[:h])
            right = rec(order[h:])
            center = 0.5 * (pts.min(0) + pts.max(0))
            radius = float(np.max(np.linalg.norm(pts - center, axis=1))) + leaf_radius
        recs[i] = (right, len(recs), center, C[idx].mean(0), radius * (1 + 1e-6), cone_code(N[idx]))
        return i

    rec(np.arange(len(P)))
    nodes = np.zeros(len(recs), NODE_DTYPE)
    for i, (right, skip, center, col, radius, cone) in enumerate(recs):
        nodes[i] = (right, skip, center, col, radius, cone)
    return nodes


def room_cloud(seed: int = 1, n_sphere: int = 260, n_floor: int = 90):
    """Points on a sphere of radius 3 (normals inward) and on a floor disc at y = −1 (normals up)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n_sphere, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ps, ns = 3.0 * d, -d
    r = 2.5 * np.sqrt(rng.random(n_floor))
    t = rng.random(n_floor) * 2 * np.pi
    pf = np.stack([r * np.cos(t), -np.ones(n_floor), r * np.sin(t)], 1)
    nf = np.tile([0.0, 1.0, 0.0], (n_floor, 1))
    P = np.concatenate([ps, pf]).astype(np.float32)
    N = np.concatenate([ns, nf]).astype(np.float32)
    C = rng.random((len(P), 3)).astype(np.float32)
    return P, N, C


def sphere_tile(h: int = 12, w: int = 10, radius: float = 0.5):
    """Orthographic G-buffer of a sphere at the origin seen from +z: (position, normal, mask)."""
    ys, xs = np.meshgrid((np.arange(h) + 0.5) / h * 1.2 - 0.6, (np.arange(w) + 0.5) / w * 1.2 - 0.6, indexing="ij")
    rr = xs ** 2 + ys ** 2
    mask = rr < radius ** 2
    z = np.sqrt(np.maximum(radius ** 2 - rr, 0))
    pos = np.stack([xs, ys, z], -1).astype(np.float32)
    nrm = (pos / radius).astype(np.float32)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    pos[~mask] = 0
    nrm[~mask] = 0
    return {"position": pos, "normal": nrm.astype(np.float32), "mask": mask}


def plane_tile(h: int = 8, w: int = 8):
    """A flat patch at y = −0.6 facing up (all normals equal: exercises node refinement at coarse levels)."""
    zs, xs = np.meshgrid(np.linspace(-0.3, 0.3, h), np.linspace(-0.3, 0.3, w), indexing="ij")
    pos = np.stack([xs, np.full_like(xs, -0.6), zs], -1).astype(np.float32)
    nrm = np.zeros_like(pos)
    nrm[..., 1] = 1
    return {"position": pos, "normal": nrm, "mask": np.ones((h, w), bool)}


CFG = GatherParams(16, stop_multiple=4.0, omega_tr=32.0, memory_budget_bytes=0.0625 * 2 ** 30)


@pytest.fixture(scope="module")
def scene():
    P, N, C = room_cloud()
    return build_tiny_bsh(P, N, C, leaf_radius=0.08)


_DECODED: dict = {}


def classic_cut(nodes: np.ndarray, p: np.ndarray, n: np.ndarray, m: int, stop_multiple: float,
                start: int = 0) -> list[int]:
    """Per-pixel stackless depth-first walk of walk.comp.glsl (float32 like the shader): the nodes it
    splats, in visiting order."""
    f = np.float32
    key = id(nodes)
    if _DECODED.get("key") != key:
        _DECODED.update(key=key, dec=pm.decode_nodes(nodes), skip=nodes["skip"].astype(np.int64))
    dec, skip = _DECODED["dec"], _DECODED["skip"]
    omega_pix = f(2 * np.pi) / f(m * m)
    out, i, end = [], start, int(skip[start])
    while i < end:
        v = (dec["center"][i] - p).astype(f)
        dist = f(np.sqrt(f((v * v).sum(dtype=f))))
        r = dec["radius"][i]
        hz = f((v * n).sum(dtype=f)) < -r
        bf = False
        if not dec["all_dirs"][i] and dist > r:
            lim = f(dec["half"][i] + f(0.5 * np.pi) + f(np.arcsin(min(r / dist, f(1)))))
            if lim < f(np.pi):
                bf = f(((-v / dist) * dec["axis"][i]).sum(dtype=f)) < f(np.cos(lim))
        if hz or bf:
            i = int(skip[i])
            continue
        om = pm.node_solid_angle(np.array([dist], f), np.array([r], f))[0]
        if dec["leaf"][i] or om <= f(stop_multiple) * omega_pix:
            out.append(i)
            i = int(skip[i])
        else:
            i += 1
    return out


# ------------------------------------------------------------------------------------------ Z-order
def test_morton_round_trip_and_children():
    rng = np.random.default_rng(0)
    x = rng.integers(0, 1 << 16, 5000)
    y = rng.integers(0, 1 << 16, 5000)
    c = pm.morton_encode(x, y)
    xd, yd = pm.morton_decode(c)
    assert np.array_equal(xd, x) and np.array_equal(yd, y)
    # independent bit-by-bit interleave
    ref = [sum((((xi >> b) & 1) << (2 * b)) | (((yi >> b) & 1) << (2 * b + 1)) for b in range(16))
           for xi, yi in zip(x[:200].tolist(), y[:200].tolist())]
    assert c[:200].tolist() == ref
    # the four children of code c one level finer are 4c + dx + 2dy
    xs, ys = x[:100] >> 1, y[:100] >> 1
    parent = pm.morton_encode(xs, ys)
    for dx in (0, 1):
        for dy in (0, 1):
            assert np.array_equal(pm.morton_encode(2 * xs + dx, 2 * ys + dy), 4 * parent + dx + 2 * dy)
    with pytest.raises(ValueError):
        pm.morton_encode(np.array([1 << 16]), np.array([0]))


# ------------------------------------------------------------------------------------------ cone mip-map
def test_cone_mipmap_contains_level0_normals_and_positions():
    rng = np.random.default_rng(3)
    h, w = 13, 10
    nrm = rng.normal(size=(h, w, 3)) + np.array([0, 0, 2.0])     # mostly +z, some wide blocks
    nrm[:4, :4] = rng.normal(size=(4, 4, 3))                       # a block of arbitrary directions
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    nrm = nrm.astype(np.float32)
    pos = rng.normal(size=(h, w, 3)).astype(np.float32)
    mask = rng.random((h, w)) > 0.25
    levels = pm.cone_mipmap(nrm, mask, pos)
    assert len(levels) == 5 and levels[-1]["mask"].shape == (1, 1)   # 16 → 1
    assert np.array_equal(levels[0]["axis"][:h, :w][mask], nrm[mask])       # level 0 is the G-buffer
    assert np.all(levels[0]["half_angle"] == 0)
    for lv in levels[1:]:
        b = 1 << lv["level"]
        k = lv["mask"].shape[0]
        for i in range(k):
            for j in range(k):
                sel = np.zeros((16, 16), bool)
                sel[i * b:(i + 1) * b, j * b:(j + 1) * b] = True
                below = sel[:h, :w] & mask
                assert lv["mask"][i, j] == bool(below.any())
                if not below.any():
                    continue
                ax = lv["axis"][i, j].astype(np.float64)
                ns = nrm[below].astype(np.float64)
                ang = np.arccos(np.clip(ns @ ax / np.linalg.norm(ax) / np.linalg.norm(ns, axis=1), -1, 1))
                assert np.all(ang <= float(lv["half_angle"][i, j]) + 1e-12)
                dist = np.linalg.norm(pos[below].astype(np.float64) - lv["center"][i, j].astype(np.float64), axis=1)
                assert np.all(dist <= float(lv["radius"][i, j]))
    # a flat region gives a (near) zero cone
    flat = pm.cone_mipmap(np.tile(np.float32([0, 1, 0]), (8, 8, 1)), np.ones((8, 8), bool))
    assert float(flat[-1]["half_angle"][0, 0]) < 1e-5
    # opposite normals: the whole sphere
    opp = np.zeros((1, 2, 3), np.float32)
    opp[0, 0, 2], opp[0, 1, 2] = 1, -1
    assert float(pm.cone_mipmap(opp, np.ones((1, 2), bool))[1]["half_angle"][0, 0]) >= np.pi - 1e-6


def test_pyramid_layout_is_z_order():
    rng = np.random.default_rng(5)
    nrm = np.tile(np.float32([0, 0, 1]), (8, 8, 1))
    mask = rng.random((8, 8)) > 0.5
    pos = rng.normal(size=(8, 8, 3)).astype(np.float32)
    pyr = pm.build_pyramid(pm.cone_mipmap(nrm, mask, pos), 8, 8)
    assert pyr.level_off.tolist() == [0, 64, 80, 84]
    yy, xx = np.nonzero(mask)
    codes = pm.morton_encode(xx, yy)
    assert np.allclose(pyr.sphere[codes, :3], pos[yy, xx])
    assert np.array_equal(np.sort(codes), pyr.level0_codes())


# ------------------------------------------------------------------------------------------ traversal (CPU)
@pytest.mark.parametrize("tile_fn", [sphere_tile, plane_tile])
def test_cpu_mipmapped_cut_equals_classic_walk(scene, tile_fn):
    tile = tile_fn()
    pix, node, st = pm.simulate_cut(tile, scene, CFG, hybrid=False)
    w = tile["mask"].shape[1]
    ys, xs = np.nonzero(tile["mask"])
    total = 0
    for y, x in zip(ys, xs):
        ref = classic_cut(scene, tile["position"][y, x], tile["normal"][y, x], 16, 4.0)
        got = node[pix == y * w + x].tolist()
        assert got == sorted(ref)           # depth-first order == node order
        total += len(ref)
    assert total == len(pix) > 0
    assert st["iterations"] > 3


@pytest.mark.parametrize("tile_fn", [sphere_tile, plane_tile])
def test_cpu_hybrid_subtrees_reproduce_classic_cut(scene, tile_fn):
    tile = tile_fn()
    pix, node, st = pm.simulate_cut(tile, scene, CFG, hybrid=True)
    w = tile["mask"].shape[1]
    ys, xs = np.nonzero(tile["mask"])
    coarse = 0
    for y, x in zip(ys, xs):
        p, n = tile["position"][y, x], tile["normal"][y, x]
        ref = classic_cut(scene, p, n, 16, 4.0)
        starts = node[pix == y * w + x].tolist()
        assert starts == sorted(set(starts))
        got = [k for s in starts for k in classic_cut(scene, p, n, 16, 4.0, start=s)]
        assert got == ref
        coarse += len(starts)
    assert st["finished_pairs"] < coarse or st["iterations"] > 0


def test_non_unit_and_zero_normals_keep_the_classic_cut(gl_context, scene):
    """The walk uses the G-buffer normal as given (dot(v, n) < −r): normals of length 0.25, 1 or 4 and a
        zero normal must still give every pixel its classic cut (the coarse margins widen by max | |n| − 1 |)."""
    tile = sphere_tile(16, 16)
    rng = np.random.default_rng(7)
    tile["normal"] = (tile["normal"] * rng.choice([0.25, 1.0, 4.0], (16, 16, 1))).astype(np.float32)
    ys, xs = np.nonzero(tile["mask"])
    tile["normal"][ys[3], xs[3]] = 0.0
    pix, node, st = pm.simulate_cut(tile, scene, CFG, hybrid=False)
    for y, x in zip(ys, xs):
        ref = classic_cut(scene, tile["position"][y, x], tile["normal"][y, x], 16, 4.0)
        assert node[pix == y * 16 + x].tolist() == sorted(ref)
    gpix, gnode, gst = pm.find_cut(gl_context, tile, gl_context.buffer(scene.tobytes()), CFG, hybrid=False)
    assert gst["pairs_per_iteration"] == st["pairs_per_iteration"]
    assert np.array_equal(gpix, pix) and np.array_equal(gnode, node)


# ------------------------------------------------------------------------------------------ traversal (GPU)
@pytest.mark.parametrize("hybrid", [False, True])
@pytest.mark.parametrize("tile_fn", [sphere_tile, plane_tile])
def test_gpu_pair_counts_equal_cpu_simulation(gl_context, scene, tile_fn, hybrid):
    tile = tile_fn()
    nodes_buf = gl_context.buffer(scene.tobytes())
    pix, node, st = pm.find_cut(gl_context, tile, nodes_buf, CFG, hybrid=hybrid)
    cpix, cnode, cst = pm.simulate_cut(tile, scene, CFG, hybrid=hybrid)
    assert st["pairs_per_iteration"] == cst["pairs_per_iteration"]
    assert st["next_per_iteration"] == cst["next_per_iteration"]
    assert st["done_per_iteration"] == cst["done_per_iteration"]
    assert np.array_equal(pix, cpix) and np.array_equal(node, cnode)
    assert st["passes"] == st["iterations"]            # everything fitted one chunk
    # sorted by (pixel, node), no duplicate pair
    key = pix.astype(np.int64) * (1 << 32) + node
    assert np.all(np.diff(key) > 0)


@pytest.mark.parametrize("hybrid", [False, True])
def test_gpu_chunking_under_tiny_budget_changes_nothing(gl_context, scene, hybrid):
    tile = sphere_tile()
    nodes_buf = gl_context.buffer(scene.tobytes())
    ref_pix, ref_node, ref = pm.find_cut(gl_context, tile, nodes_buf, CFG, hybrid=hybrid)
    budget = 9 * 8 * 50                                 # 50 input pairs a pass
    pix, node, st = pm.find_cut(gl_context, tile, nodes_buf, CFG, hybrid=hybrid, tf_budget=budget)
    assert np.array_equal(pix, ref_pix) and np.array_equal(node, ref_node)
    assert st["pairs_per_iteration"] == ref["pairs_per_iteration"]
    assert st["passes"] > st["iterations"] and st["host_spills"] > 0
    assert 0 < st["peak_tf_bytes"] <= budget
    assert max(ref["pairs_per_iteration"]) > 50         # the budget did bind


def test_gpu_empty_tile(gl_context, scene):
    tile = sphere_tile()
    tile["mask"][:] = False
    nodes_buf = gl_context.buffer(scene.tobytes())
    pix, node, st = pm.find_cut(gl_context, tile, nodes_buf, CFG, hybrid=True)
    assert len(pix) == 0 and len(node) == 0 and st["iterations"] == 0


# ------------------------------------------------------------------------------------------ with relight's gather
@pytest.mark.parametrize("method", ["mipmapped", "hybrid"])
def test_gather_mipmapped_hybrid_equal_classic(gl_context, scene, method):
    """Same micro-buffers, same radiance (the classic walk vs the gatherer's start lists from the cut)."""
    tile = sphere_tile(14, 14)
    mask = tile["mask"]
    flat = np.flatnonzero(mask)
    P = len(flat)
    pos = tile["position"].reshape(-1, 3)[flat]
    nrm = tile["normal"].reshape(-1, 3)[flat]
    view = np.tile(np.float32([0, 0, 1]), (P, 1))
    recv = Receivers(pos, nrm, view, np.full((P, 3), 0.8, np.float32), np.zeros(P, np.float32),
                     np.full(P, 0.5, np.float32))
    per = 16 * 16 * 16                                          # micro-buffer bytes a receiver
    g = ClassicGatherer(gl_context, scene, dataclasses.replace(CFG, brdf="ggx", memory_budget_bytes=-(-P // 3) * per))
    g.keep_microbuffers = True
    classic, st_c = g.run(recv)
    # the same three gather tiles: the cut gatherers keep GATHER_SHARE of the budget for the walk
    gm = GATHERERS[method](gl_context, scene, dataclasses.replace(
        CFG, brdf="ggx", memory_budget_bytes=(-(-P // 3) + 0.5) * per / GATHERERS[method].GATHER_SHARE))
    gm.keep_microbuffers = True
    got, st_m = gm.run(recv, flat, mask.shape)
    cut = st_m["cut"]
    assert st_c["tiles"] == st_m["tiles"] == 3 and cut["blocks"] >= 3
    assert np.array_equal(gm.last_microbuffers, g.last_microbuffers)
    rel_rms = np.sqrt(np.mean((got - classic) ** 2)) / np.sqrt(np.mean(classic ** 2))
    assert rel_rms <= 0.01 and np.all(np.isfinite(got))
    assert st_m["start_nodes"] == cut["output_pairs"]
    if method == "mipmapped":       # every start node is splatted at once: visits == start nodes
        assert st_m["nodes_visited"] == st_m["start_nodes"]
    else:
        assert st_m["nodes_visited"] <= st_c["nodes_visited"]


# ------------------------------------------------------------------------------------------ through the real CLI
def _room_scene(tmp_path):
    """A coloured room BSH, a sphere object and a scene.json with one 24×20 view."""
    import trimesh

    from bsh_builders import simple_bsh_arrays
    from pipeline import io

    P, N, C = room_cloud(seed=2, n_sphere=900, n_floor=300)
    C[:40] *= 30.0                                                  # a few bright points
    io.write_npz(tmp_path / "bsh.npz", "pcrelight.bsh/1", **simple_bsh_arrays(P, N, C, 0.12))
    tm = trimesh.creation.icosphere(2, radius=1.0)
    io.write_mesh(tmp_path / "object.ply", tm.vertices, tm.faces, tm.vertex_normals)
    M = np.eye(4)
    M[:3, :3] *= 0.4
    scene = {"views": {"view1": {"eye": [0.3, 0.5, 1.6], "target": [0, 0, 0], "up": [0, 1, 0], "fov_deg": 40.0,
                                 "size": [24, 20]}},
             "object": {"file": "object.ply", "to_world": M.tolist(), "center": [0, 0, 0], "radius": 0.4}}
    io.write_json(tmp_path / "scene.json", scene)


def _relight(cli_run, tmp_path, out, method, *extra):
    from pipeline import io

    code, _, err = cli_run("relight", "--bsh", tmp_path / "bsh.npz", "--scene", tmp_path / "scene.json",
                           "--view", "view1", "--microbuffer", "16", "--method", method, "--brdf", "ggx",
                           "--roughness", "0.3", "--out", out, "-q", *extra)
    assert code == 0, err
    return io.read_image(out / "relit.exr"), io.read_json(out / "stats.json")


def test_start_lists_over_the_limit_are_walked_in_sub_ranges(tmp_path, cli_run):
    """A memory budget so small that one tile's mipmapped start lists exceed budget/4: the gather
    walks the tile in receiver sub-ranges and the image is the same as classic's. (No lobe buffer: its texels
    would share the budget, the tiles shrink and their start lists no longer exceed it.)"""
    _room_scene(tmp_path)
    ref, _ = _relight(cli_run, tmp_path, tmp_path / "classic", "classic", "--microbuffer", "8", "--lobe-buffer", "0")
    img, st = _relight(cli_run, tmp_path, tmp_path / "mip", "mipmapped", "--microbuffer", "8", "--memory-budget", "0.00005",
                       "--lobe-buffer", "0")
    assert st["start_list_splits"] > 0 and st["start_nodes"] * 4 > st["start_list_limit_bytes"]
    assert np.array_equal(img, ref)
    # with the lobe buffer (default): the same budget tiles it finer, and the image is still classic's
    ref, _ = _relight(cli_run, tmp_path, tmp_path / "classic_lobe", "classic", "--microbuffer", "8")
    img, st = _relight(cli_run, tmp_path, tmp_path / "mip_lobe", "mipmapped", "--microbuffer", "8", "--memory-budget",
                       "0.00005")
    assert st["tiles"] > 1 and np.array_equal(img, ref)


def test_cli_relight_methods_agree(tmp_path, cli_run):
    """pcrelight relight --method classic|mipmapped|hybrid on a coloured room: the same relit.exr
    (relative RMS ≤ 1 %; the construction makes it exact), stats.json carries the cut statistics."""
    _room_scene(tmp_path)
    imgs, stats = {}, {}
    for method in ("classic", "mipmapped", "hybrid"):
        imgs[method], stats[method] = _relight(cli_run, tmp_path, tmp_path / method, method)
    ref = imgs["classic"]
    assert (ref[..., 3] > 0).sum() > 50
    for method in ("mipmapped", "hybrid"):
        rel = np.sqrt(np.mean((imgs[method] - ref) ** 2)) / np.sqrt(np.mean(ref ** 2))
        assert rel <= 0.01, (method, rel)
        cut = stats[method]["mipmapped"]
        assert cut["method"] == method and cut["iterations"] > 0 and cut["peak_tf_bytes"] > 0
        assert sum(cut["pairs_per_iteration"]) > 0
        assert stats[method]["start_nodes"] == cut["output_pairs"]
