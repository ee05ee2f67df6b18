"""pipeline/bsh/format.py is the one source of the node format and the SSBO bindings: the GLSL struct
Node has NODE_DTYPE's layout, no shader spells a binding number, every binding name a shader uses is in
the tables, and pbgi_cone_decode on the GPU equals decode_cones(float32)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from pipeline import gl
from pipeline.bsh.format import CUT_BINDINGS, GATHER_BINDINGS, IMAGE_BINDINGS, NODE_BYTES, NODE_DTYPE, decode_cones
from pipeline.bsh.cones import pack_cones

GATHER = Path(__file__).resolve().parents[1] / "pipeline" / "gather"
GLSL_TYPES = {"uint": "<u4", "float": "<f4"}


def test_glsl_node_struct_is_node_dtype():
    src = (GATHER / "pbgi_common.glsl").read_text()
    body = re.search(r"struct Node \{(.*?)\};", src, re.S).group(1)
    glsl = []                                   # (numpy type, number of scalars) per declaration line
    for decl in filter(None, (d.strip() for d in body.split(";"))):
        tp, names = decl.split(None, 1)
        glsl.append((GLSL_TYPES[tp], len(names.split(","))))
    want = [(NODE_DTYPE.fields[k][0].base.str, int(np.prod(NODE_DTYPE.fields[k][0].shape))) for k in NODE_DTYPE.names]
    assert glsl == want
    offs = [NODE_DTYPE.fields[k][1] for k in NODE_DTYPE.names]
    assert offs == list(np.cumsum([0] + [4 * n for _, n in want])[:-1]) and NODE_DTYPE.itemsize == NODE_BYTES == 40


def test_shaders_use_binding_names_from_the_tables():
    tables = {"walk.comp.glsl": GATHER_BINDINGS, "eq9.comp.glsl": GATHER_BINDINGS, "cut.geom.glsl": CUT_BINDINGS,
              "envmap.shade.comp.glsl": GATHER_BINDINGS, "envmap.prefilter.comp.glsl": IMAGE_BINDINGS,
              "envmap.lut.comp.glsl": IMAGE_BINDINGS, "importance.comp.glsl": GATHER_BINDINGS}
    common = set(re.findall(r"binding = PBGI_BIND_(\w+)", (GATHER / "pbgi_common.glsl").read_text()))
    for f in GATHER.glob("*.glsl"):
        src = f.read_text()
        assert not re.search(r"binding\s*=\s*\d", src), f"{f.name} spells a binding number"
        if f.name in tables:                    # a missing name would not compile (the gather tests run them)
            used = set(re.findall(r"binding = PBGI_BIND_(\w+)", src))
            assert used and used <= set(tables[f.name]), (f.name, used - set(tables[f.name]))
    assert common <= set(GATHER_BINDINGS) and "NODES" in CUT_BINDINGS   # the cut includes the node buffer only
    assert len(set(GATHER_BINDINGS.values())) == len(GATHER_BINDINGS)
    assert len(set(CUT_BINDINGS.values())) == len(CUT_BINDINGS)


def test_gpu_cone_decode_equals_decode_cones(gl_context):
    rng = np.random.default_rng(3)
    axis = rng.normal(size=(1000, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    packed = pack_cones(axis, rng.random(1000) * np.pi * 1.1)[0]
    packed = np.concatenate([packed, np.uint32([0x7F7F7F00, 0xFF808080, 0])])    # zero-ish axes, all directions
    src = ("#version 430\n#define PBGI_NO_NODE_BUFFER\n" + gl.load_glsl("pbgi_common.glsl", GATHER) + """
layout(local_size_x = 64) in;
layout(std430, binding = 0) readonly buffer In { uint cones[]; };
layout(std430, binding = 1) writeonly buffer Out { vec4 outp[]; };
uniform uint n;
void main() {
    uint i = gl_GlobalInvocationID.x;
    if (i >= n) return;
    vec3 a; float h;
    pbgi_cone_decode(cones[i], a, h);
    outp[i] = vec4(a, h);
}""")
    prog = gl_context.compute_shader(src)
    bi = gl_context.buffer(packed.astype(np.uint32).tobytes())
    bo = gl_context.buffer(reserve=16 * len(packed))
    bi.bind_to_storage_buffer(0)
    bo.bind_to_storage_buffer(1)
    prog["n"].value = len(packed)
    prog.run(group_x=(len(packed) + 63) // 64)
    got = np.frombuffer(bo.read(), np.float32).reshape(-1, 4)
    ax, half = decode_cones(packed, np.float32)
    assert ax.dtype == half.dtype == np.float32
    np.testing.assert_allclose(got[:, :3], ax, atol=2e-7)
    np.testing.assert_allclose(got[:, 3], half, atol=4e-7)
    assert np.all(half[(packed >> 24) == 255] == np.float32(np.pi))


def test_bsh_file_leaves_derived_members_to_the_nodes(tmp_path):
    """build-bsh's bsh.npz holds no member of DERIVED_KEYS; io.read_npz gives them back equal, byte for byte, to
    what build_bsh returned (the stored decoded cone included: the half-angle rounded up to float32), or only the
    members asked for (``keys``), and a file whose node records are not a depth-first tree, or whose counts are not
    their leaves' sums, is refused in one line."""
    import zipfile

    import pytest

    from pipeline.bsh.format import DERIVED_KEYS, derived_arrays
    from pipeline.bsh.build_bsh import write_bsh
    from pipeline.bsh.builder import build_bsh
    from pipeline.errors import InputError
    from pipeline.io import read_npz, write_npz

    rng = np.random.default_rng(3)
    p = rng.random((4000, 3)).astype(np.float32)
    p[:, 2] *= 0.05                                 # a noisy slab: cones of every width, clusters and leaves
    n = rng.normal(size=(4000, 3)).astype(np.float32)
    n[:, 2] += 4.0
    c = rng.random((4000, 3)).astype(np.float32)
    r = build_bsh(p, n, c, tc=0.05, tn=0.9)
    r.pop("stats")
    assert r["cluster"].any() and (r["child"][:, 0] >= 0).any() and (r["cone_half_angle"] < 3.0).any()
    write_bsh(tmp_path / "b.npz", r)
    with zipfile.ZipFile(tmp_path / "b.npz") as zf:
        names = {i.filename[:-4] for i in zf.infolist()}
    assert names == set(r) - set(DERIVED_KEYS) | {"schema"}
    got = read_npz(tmp_path / "b.npz", "pcrelight.bsh/1")
    assert sorted(got) == sorted(r)
    for k in r:
        a = np.asarray(r[k])
        assert got[k].dtype == a.dtype and got[k].shape == a.shape and got[k].tobytes() == a.tobytes(), k
    part = read_npz(tmp_path / "b.npz", "pcrelight.bsh/1", keys=("nodes", "splat_radius", "emitters"))  # relight's
    assert sorted(part) == ["emitters", "nodes", "splat_radius"]
    assert all(part[k].tobytes() == np.asarray(r[k]).tobytes() for k in part)
    assert read_npz(tmp_path / "b.npz", "pcrelight.bsh/1", keys=("depth", "count"))["depth"].tobytes() == \
        r["depth"].tobytes()
    bad = np.array(r["nodes"]).view(NODE_DTYPE)
    bad["right"][0] = 0                             # the root its own right child: a cycle
    arrays = {k: v for k, v in r.items() if k not in DERIVED_KEYS}
    arrays["nodes"] = bad
    write_npz(tmp_path / "bad.npz", "pcrelight.bsh/1", **arrays)
    with pytest.raises(InputError, match="not a depth-first tree"):
        read_npz(tmp_path / "bad.npz", "pcrelight.bsh/1")
    with pytest.raises(InputError, match="not a depth-first tree"):
        derived_arrays(bad[:-1], r["count"][:-1])
    cnt = r["count"].copy()
    cnt[np.flatnonzero(r["child"][:, 0] >= 0)[1]] += 1  # an inner node's count not its leaves' sum
    arrays = {k: v for k, v in r.items() if k not in DERIVED_KEYS}
    arrays["count"] = cnt
    write_npz(tmp_path / "bad.npz", "pcrelight.bsh/1", **arrays)
    with pytest.raises(InputError, match="'count' is not the sum"):
        read_npz(tmp_path / "bad.npz", "pcrelight.bsh/1")


def test_all_directions_cone_is_pack_cones_of_a_full_sphere():
    """The joining roots' constant cone (no numba load in relight) is what pack_cones packs for half-angle π, and
    it decodes to all directions."""
    from pipeline.bsh.format import ALL_DIRECTIONS_CONE

    packed, _, _ = pack_cones(np.array([[0.0, 0.0, 1.0]]), np.array([np.pi]))
    assert int(packed[0]) == ALL_DIRECTIONS_CONE
    _, half = decode_cones(np.array([ALL_DIRECTIONS_CONE], np.uint32))
    assert half[0] == np.pi
