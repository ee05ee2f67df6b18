"""Property tests of every reader (issue 30): any generated or mutated file gives a valid object or one
clean error line ``<file>: <problem>`` (InputError / ConfigError) — never another exception or a hang.

Bounded in ``make test`` (``FUZZ_EXAMPLES`` examples a reader, derandomised, a deadline per example);
``make fuzz`` sets ``PCRELIGHT_FUZZ_EXAMPLES`` (e.g. 2000) and draws fresh random inputs. The inputs
tried per reader are counted; with ``PCRELIGHT_FUZZ_REPORT=FILE`` the counts are written there as JSON.
Crashes found by fuzzing are kept below as explicit regression examples (``@example`` / ``REGRESSIONS``).
"""

from __future__ import annotations

import io as _io
import json
import math
import os
import signal
import struct
import zipfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis", reason="hypothesis not installed (pip install -e '.[dev]')")
from hypothesis import HealthCheck, example, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from pipeline import io  # noqa: E402
from pipeline.errors import ConfigError, InputError, PcrelightError  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "data_samples"
LONG = int(os.environ.get("PCRELIGHT_FUZZ_EXAMPLES", "0"))
FUZZ_EXAMPLES = LONG or 12
HANG_S = 20.0   # an example that runs longer than this counts as a hang
COUNTS: dict[str, dict[str, int]] = {}

SETTINGS = settings(max_examples=FUZZ_EXAMPLES, deadline=None if LONG else 5000, derandomize=not LONG,
                    database=None, suppress_health_check=list(HealthCheck), print_blob=True)


@pytest.fixture(scope="module", autouse=True)
def _report_counts():
    """Caps this process's address space while the readers are fuzzed (a reader that allocates for a
    lying header fails with MemoryError instead of swapping the machine) and writes the counts."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    cap = 6 * 2 ** 30
    if soft == resource.RLIM_INFINITY or soft > cap:
        resource.setrlimit(resource.RLIMIT_AS, (cap, hard))
    yield
    resource.setrlimit(resource.RLIMIT_AS, (soft, hard))
    out = os.environ.get("PCRELIGHT_FUZZ_REPORT")
    if out:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        old = json.loads(Path(out).read_text()) if Path(out).exists() else {}
        old.update(COUNTS)
        Path(out).write_text(json.dumps(old, indent=2, sort_keys=True) + "\n")


@contextmanager
def _no_hang(what: str):
    def alarm(signum, frame):  # noqa: ARG001
        raise TimeoutError(f"{what}: no answer within {HANG_S} s (a hang)")

    old = signal.signal(signal.SIGALRM, alarm)
    signal.setitimer(signal.ITIMER_REAL, HANG_S)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def check_reader(reader: str, path: Path, call, valid=None) -> None:
    """``call()`` must return (then ``valid(result)`` must hold) or raise a one-line PcrelightError that
    names ``path``; anything else fails the property."""
    c = COUNTS.setdefault(reader, {"inputs": 0, "valid": 0, "clean_error": 0})
    c["inputs"] += 1
    try:
        with _no_hang(reader):
            res = call()
    except (InputError, ConfigError) as e:
        msg = str(e)
        assert "\n" not in msg, f"{reader}: multi-line error {msg!r}"
        assert msg.strip(), f"{reader}: empty error"
        if isinstance(e, InputError) and e.path is not None:
            assert Path(e.path).name in {path.name} | {x.name for x in path.parent.iterdir()}, msg
        c["clean_error"] += 1
        return
    except PcrelightError as e:
        pytest.fail(f"{reader}: unexpected {type(e).__name__}: {e}")
    if valid is not None:
        valid(res)
    c["valid"] += 1


def mutate(data: bytes, ops: list[tuple[int, int, int]]) -> bytes:
    """Apply (kind, position, value) edits: 0 flip a byte, 1 truncate, 2 insert, 3 delete 1..8 bytes,
    4 overwrite 4 bytes with a little-endian int32 (counts and lengths are a favourite)."""
    b = bytearray(data)
    for kind, pos, val in ops:
        if not b:
            break
        i = pos % len(b)
        if kind == 0:
            b[i] ^= (val % 255) + 1
        elif kind == 1:
            del b[i:]
        elif kind == 2:
            b[i:i] = bytes([val % 256]) * (1 + val % 7)
        elif kind == 3:
            del b[i:i + 1 + val % 8]
        else:
            b[i:i + 4] = struct.pack("<i", [0, -1, 1, 2 ** 31 - 1, -2 ** 31, 65536, val][val % 7])
    return bytes(b)


OPS = st.lists(st.tuples(st.integers(0, 4), st.integers(0, 2 ** 20), st.integers(0, 2 ** 31 - 1)), min_size=1, max_size=6)
NUMS = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=32), st.integers(-10 ** 6, 10 ** 6),
                 st.sampled_from([0.0, 1.0, -1.0, 1e38, -1e38, 3.4e39]))


# ------------------------------------------------------------------------------------------- PLY
def _cloud_valid(c: io.Cloud) -> None:
    c.validate("<fuzz>")
    assert len(c) > 0 and c.points.dtype == np.float32 and c.colors.dtype == np.float32
    ln = np.linalg.norm(c.normals, axis=1)
    assert np.all(np.abs(ln - 1) < 1e-3), "normals are not unit length"


def _ply_seed(tmp: Path, text: bool, uchar: bool = False) -> bytes:
    rng = np.random.default_rng(1)
    p = rng.normal(size=(8, 3)).astype(np.float32)
    n = -p / np.linalg.norm(p, axis=1, keepdims=True)
    cl = io.Cloud(p, n.astype(np.float32), rng.uniform(0, 2, (8, 3)).astype(np.float32),
                  valid=np.ones(8, np.uint8), quality=np.zeros(8, np.float32), source=np.zeros(8, np.uint8))
    f = tmp / "seed.ply"
    io.write_cloud(f, cl, uchar_colors=uchar)
    if not text:
        return f.read_bytes()
    from plyfile import PlyData

    ply = PlyData.read(str(f))  # (memory-maps f: write the ASCII copy elsewhere)
    ply.text = True
    ply.write(str(tmp / "seed_ascii.ply"))
    return (tmp / "seed_ascii.ply").read_bytes()


PLY_TYPES = ["float", "double", "uchar", "char", "short", "ushort", "int", "uint", "float32", "int8", "list uchar float"]
PLY_PROPS = ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue", "r", "g", "b", "valid", "quality", "source", "alpha"]


@st.composite
def ply_files(draw) -> bytes:
    """A PLY written from scratch: random properties and types, a vertex count that may lie, ASCII
    numbers (NaN, Inf, huge) or binary bytes."""
    props = draw(st.lists(st.sampled_from(PLY_PROPS), min_size=0, max_size=12))
    types = [draw(st.sampled_from(PLY_TYPES)) for _ in props]
    fmt = draw(st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian"]))
    n_decl = draw(st.sampled_from([0, 1, 2, 3, 5, 40, -1, 2 ** 31]))
    n_rows = draw(st.integers(0, 6))
    head = f"ply\nformat {fmt} 1.0\nelement vertex {n_decl}\n" + "".join(
        f"property {t} {p}\n" for p, t in zip(props, types))
    if draw(st.booleans()):
        head += "element face 1\nproperty list uchar int vertex_indices\n"
    head += "end_header\n"
    if fmt == "ascii":
        rows = [" ".join(str(draw(NUMS)) for _ in range(max(1, len(props)))) for _ in range(n_rows)]
        body = ("\n".join(rows) + "\n").encode()
    else:
        body = draw(st.binary(max_size=400))
    return head.encode() + body


@SETTINGS
@given(data=ply_files())
@example(data=b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
              b"property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n0 0 0 300 -5 1e9\n")
@example(data=b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
              b"property float red\nproperty float green\nproperty float blue\nend_header\n0 0 0 1 1 1\n0 0 0 1 1 1\n")
def test_ply_reader_generated(tmp_path_factory, data):
    d = tmp_path_factory.mktemp("ply")
    f = d / "c.ply"
    f.write_bytes(data)
    check_reader("PLY (io.read_cloud)", f, lambda: io.read_cloud(f), _cloud_valid)


@SETTINGS
@given(text=st.booleans(), uchar=st.booleans(), ops=OPS)
@example(text=False, uchar=True, ops=[(2, 91971, 0)])  # found by fuzzing: float32 norm of huge normals overflowed → 0-length
def test_ply_reader_mutated(tmp_path_factory, text, uchar, ops):
    d = tmp_path_factory.mktemp("plym")
    f = d / "c.ply"
    f.write_bytes(mutate(_ply_seed(d, text, uchar), ops))
    check_reader("PLY (io.read_cloud)", f, lambda: io.read_cloud(f), _cloud_valid)


# ------------------------------------------------------------------------------------------- images
def _image_valid(a: np.ndarray) -> None:
    assert a.dtype == np.float32 and a.ndim == 3 and min(a.shape) >= 1
    assert np.all(np.isfinite(a)), "an image with NaN/Inf pixels was accepted"


_IMG_SEEDS: dict[str, bytes] = {}


def _image_seed(ext: str, d: Path) -> bytes:
    if ext not in _IMG_SEEDS:
        rng = np.random.default_rng(2)
        f = d / f"seed.{ext}"
        if ext == "png":
            io.write_png(f, rng.uniform(0, 1, (6, 5, 3)))
        else:
            io.write_image(f, rng.uniform(0, 4, (6, 5, 4 if ext == "exr" else 3)).astype(np.float32))
        _IMG_SEEDS[ext] = f.read_bytes()
    return _IMG_SEEDS[ext]


@SETTINGS
@given(ext=st.sampled_from(["exr", "hdr", "png"]), ops=OPS)
@example(ext="exr", ops=[(0, 15, 225)])  # found by fuzzing: a 0xe2 in an attribute name made OIIO's geterror() raise UnicodeDecodeError
def test_image_reader_mutated(tmp_path_factory, ext, ops):
    d = tmp_path_factory.mktemp("img")
    f = d / f"photo.{ext}"
    f.write_bytes(mutate(_image_seed(ext, d), ops))
    check_reader("EXR/HDR/PNG (io.read_image)", f, lambda: io.read_image(f), _image_valid)


@SETTINGS
@given(ext=st.sampled_from(["exr", "hdr"]), head=st.sampled_from([b"", b"v/1\x01", b"#?RADIANCE\n", b"#?RGBE\n"]),
       body=st.binary(max_size=300))
def test_image_reader_random_bytes(tmp_path_factory, ext, head, body):
    f = tmp_path_factory.mktemp("imgr") / f"photo.{ext}"
    f.write_bytes(head + body)
    check_reader("EXR/HDR/PNG (io.read_image)", f, lambda: io.read_image(f), _image_valid)


PIXELS = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=32), st.sampled_from([0.0, 1.0, 65504.0, 65520.0, 1e6, -1e6]))


@SETTINGS
@given(fmt=st.sampled_from(["float", "half"]), size=st.tuples(st.integers(1, 6), st.integers(1, 6), st.sampled_from([1, 3, 4, 5])),
       cells=st.lists(st.tuples(st.integers(0, 2 ** 16), PIXELS), max_size=8))
@example(fmt="half", size=(2, 2, 3), cells=[(1, 1e6)])  # 1e6 overflows half to Inf
@example(fmt="float", size=(1, 1, 1), cells=[(0, float("nan"))])
def test_image_reader_special_values(tmp_path_factory, fmt, size, cells):
    """A well-formed EXR (as another tool writes it, float or half) with any values in its pixels: NaN and
    ±Inf (also a half overflowed to Inf) give one line; finite values read back."""
    import OpenImageIO as oiio

    h, w, c = size
    img = np.ones(size, np.float32)
    for i, v in cells:
        img.flat[i % img.size] = v
    f = tmp_path_factory.mktemp("imgv") / "photo.exr"
    out = oiio.ImageOutput.create(str(f))
    out.open(str(f), oiio.ImageSpec(w, h, c, fmt))
    out.write_image(img)
    out.close()
    with np.errstate(over="ignore"):
        stored = img.astype(np.float16).astype(np.float32) if fmt == "half" else img

    def valid(a: np.ndarray) -> None:  # (accepting a NaN/Inf pixel fails here)
        _image_valid(a)
        assert np.array_equal(a, stored), "finite pixels did not read back as stored"

    check_reader("EXR/HDR/PNG (io.read_image)", f, lambda: io.read_image(f), valid)


# ------------------------------------------------------------------------------------------- NPZ
def _npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    buf = _io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for k, a in arrays.items():
            b = _io.BytesIO()
            np.lib.format.write_array(b, a, allow_pickle=True)
            zf.writestr(k + ".npy", b.getvalue())
    return buf.getvalue()


def _schema_names() -> list[str]:
    from pipeline.schemas import SCHEMAS

    return sorted(SCHEMAS)


DTYPES = ["float64", "float32", "int32", "int64", "uint8", "bool", "U8", "V40", "object"]


@st.composite
def npz_files(draw) -> tuple[str, bytes]:
    from pipeline.schemas import SCHEMAS

    schema = draw(st.sampled_from(_schema_names()))
    keys = list(SCHEMAS[schema])
    arrays: dict[str, np.ndarray] = {}
    if draw(st.integers(0, 9)):
        arrays["schema"] = np.asarray(draw(st.sampled_from([schema, *_schema_names(), "x", ""])))
    for k in draw(st.lists(st.sampled_from(keys + ["extra"]), max_size=len(keys) + 1, unique=True)):
        spec = SCHEMAS[schema].get(k)
        dt = draw(st.sampled_from(DTYPES + ([spec[0]] * 3 if spec and spec[0] not in ("str",) and not spec[0].startswith("void") else [])))
        ndim = draw(st.integers(0, 3))
        shape = tuple(draw(st.integers(0, 3)) for _ in range(ndim))
        if spec and draw(st.booleans()):  # the schema's own shape, sizes drawn
            shape = tuple(d if isinstance(d, int) else draw(st.integers(0, 3)) for d in spec[1])
        if dt == "object":
            a = np.empty(shape, object)
        elif dt.startswith("V"):
            a = np.zeros(shape, dt)
        else:
            a = np.zeros(shape, dt)
            if a.dtype.kind == "f" and a.size:
                a.flat[0] = draw(st.sampled_from([np.nan, np.inf, -1.0, 0.5]))
        arrays[k] = a
    data = _npz_bytes(arrays)
    if draw(st.integers(0, 3)) == 0:
        data = mutate(data, draw(OPS))
    return schema, data


@SETTINGS
@given(case=npz_files())
def test_npz_reader(tmp_path_factory, case):
    schema, data = case
    f = tmp_path_factory.mktemp("npz") / "x.npz"
    f.write_bytes(data)
    check_reader("NPZ (io.read_npz)", f, lambda: io.read_npz(f, schema), lambda r: isinstance(r, dict))


@SETTINGS
@given(ops=OPS)
@example(ops=[(0, 87, 3)])  # found by fuzzing: zlib.error from a flipped byte in the deflate stream
def test_npz_reader_mutated_real_file(tmp_path_factory, ops):
    d = tmp_path_factory.mktemp("npzm")
    seed = d / "seed.npz"
    io.write_npz(seed, "pcrelight.exposure/1", **_exposure_arrays())
    f = d / "x.npz"
    f.write_bytes(mutate(seed.read_bytes(), ops))
    check_reader("NPZ (io.read_npz)", f, lambda: io.read_npz(f, "pcrelight.exposure/1"), lambda r: isinstance(r, dict))


def _exposure_arrays() -> dict[str, np.ndarray]:
    from pipeline.schemas import SCHEMAS

    out = {}
    for k, entry in SCHEMAS["pcrelight.exposure/1"].items():
        if len(entry) > 2 and entry[2] == "optional":
            continue
        dt, shape = entry[0], entry[1]
        shape = tuple(d if isinstance(d, int) else 2 for d in shape)
        out[k] = np.asarray("x") if dt == "str" else np.ones(shape, dt)
    return out


# ------------------------------------------------------------------------------------------- objects
def _object_valid(parts: list[dict]) -> None:
    assert parts
    for p in parts:
        v, f = p["positions"], p["faces"]
        assert v.ndim == 2 and v.shape[1] == 3 and np.all(np.isfinite(v))
        assert f.ndim == 2 and f.shape[1] == 3 and len(f) and int(f.max()) < len(v)
        assert np.all((p["base_color"] >= 0) & (p["base_color"] <= 1))
        assert 0 <= p["metallic"] <= 1 and 0 <= p["roughness"] <= 1
        if p["normals"] is not None:
            assert np.all(np.isfinite(p["normals"]))
        if p["uv"] is not None:
            assert np.all(np.isfinite(p["uv"]))


OBJ_NUM = st.one_of(st.floats(-10, 10, width=32), st.sampled_from(["nan", "inf", "-inf", "1e39", "x", ""]))


@st.composite
def obj_files(draw) -> tuple[str, str]:
    lines = ["mtllib o.mtl"] if draw(st.booleans()) else []
    for _ in range(draw(st.integers(0, 14))):
        kind = draw(st.sampled_from(["v", "v", "v", "vn", "vt", "f", "f", "usemtl m", "o a", "g b", "s 1"]))
        if kind in ("v", "vn"):
            lines.append(f"{kind} " + " ".join(str(draw(OBJ_NUM)) for _ in range(draw(st.integers(0, 4)))))
        elif kind == "vt":
            lines.append("vt " + " ".join(str(draw(OBJ_NUM)) for _ in range(2)))
        elif kind == "f":
            idx = st.sampled_from(["1", "2", "3", "4", "-1", "0", "99", "1/1", "2//2", "3/3/3", "a"])
            lines.append("f " + " ".join(draw(idx) for _ in range(draw(st.integers(0, 5)))))
        else:
            lines.append(kind)
    mtl = ["newmtl m"]
    for key in draw(st.lists(st.sampled_from(["Kd", "Ka", "Ks", "Ke", "Ns", "d", "Pr", "Pm", "map_Kd"]), max_size=4)):
        if key == "map_Kd":
            mtl.append("map_Kd missing.png")
        else:
            mtl.append(f"{key} " + " ".join(str(draw(OBJ_NUM)) for _ in range(draw(st.integers(0, 3)))))
    return "\n".join(lines) + "\n", "\n".join(mtl) + "\n"


@SETTINGS
@given(case=obj_files())
@example(case=("mtllib o.mtl\nusemtl m\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "newmtl m\nKd 2 0.5 0.5\n"))
@example(case=("v 0 0 0\nv 1 0 0\nv 0 1 0\nvn nan 0 0\nvn 0 1 0\nvn 0 0 1\nf 1//1 2//2 3//3\n", ""))
@example(case=("f 1 1 1\nv \nv \n", "newmtl m\n"))  # found by fuzzing: (N, 0) vertices crashed the transform
def test_obj_reader(tmp_path_factory, case):
    obj, mtl = case
    d = tmp_path_factory.mktemp("obj")
    (d / "o.mtl").write_text(mtl)
    f = d / "o.obj"
    f.write_text(obj)
    check_reader("glTF/OBJ (io.read_object)", f, lambda: io.read_object(f), _object_valid)


def _gltf_seed() -> dict:
    """A one-triangle glTF with a material, a node and embedded buffer (data URI)."""
    import base64

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32).tobytes()
    i = np.array([0, 1, 2], np.uint16).tobytes() + b"\0\0"
    buf = v + i
    return {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "scale": [1, 1, 1]}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "material": 0}]}],
        "materials": [{"name": "m", "pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 0.5, 1], "metallicFactor": 0.0,
                                                             "roughnessFactor": 0.5}}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3", "min": [0, 0, 0], "max": [1, 1, 0]},
                      {"bufferView": 1, "componentType": 5123, "count": 3, "type": "SCALAR"}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 36}, {"buffer": 0, "byteOffset": 36, "byteLength": 6}],
        "buffers": [{"byteLength": len(buf), "uri": "data:application/octet-stream;base64," + base64.b64encode(buf).decode()}],
    }


GLTF_PATHS = [("materials", 0, "pbrMetallicRoughness", "baseColorFactor"), ("materials", 0, "pbrMetallicRoughness", "metallicFactor"),
              ("materials", 0, "pbrMetallicRoughness", "roughnessFactor"), ("materials", 0, "emissiveFactor"),
              ("materials", 0, "doubleSided"), ("nodes", 0, "scale"), ("nodes", 0, "matrix"), ("nodes", 0, "translation"),
              ("nodes", 0, "mesh"), ("accessors", 0, "count"), ("accessors", 1, "count"), ("accessors", 0, "componentType"),
              ("accessors", 0, "type"), ("bufferViews", 0, "byteLength"), ("bufferViews", 1, "byteOffset"),
              ("meshes", 0, "primitives", 0, "indices"), ("meshes", 0, "primitives", 0, "material"), ("materials", 0),
              ("scenes", 0, "nodes"), ("buffers", 0, "byteLength"), ("materials",)]
JSON_VALS = st.one_of(st.none(), st.booleans(), st.integers(-5, 2 ** 33), st.floats(allow_nan=True, allow_infinity=True),
                      st.text(max_size=4), st.lists(st.floats(-2, 2), max_size=17), st.just([0, 0, 0]),
                      st.just([1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]), st.builds(dict))


def _set(doc: dict, path: tuple, value) -> None:
    o = doc
    for k in path[:-1]:
        o = o[k]
    o[path[-1]] = value


@SETTINGS
@given(edits=st.lists(st.tuples(st.sampled_from(GLTF_PATHS), JSON_VALS), min_size=1, max_size=3), glb=st.booleans(),
       ops=st.one_of(st.none(), OPS))
@example(edits=[(("nodes", 0, "scale"), [0, 0, 0])], glb=False, ops=None)
@example(edits=[(("materials", 0, "pbrMetallicRoughness", "roughnessFactor"), 1.5)], glb=True, ops=None)
def test_gltf_reader(tmp_path_factory, edits, glb, ops):
    doc = _gltf_seed()
    for path, value in edits:
        try:
            _set(doc, path, value)
        except (KeyError, IndexError, TypeError):
            pass
    d = tmp_path_factory.mktemp("gltf")
    js = json.dumps(doc).encode()  # NaN/Infinity written as such: Python's json reads them back
    if glb:
        js += b" " * (-len(js) % 4)
        data = struct.pack("<III", 0x46546C67, 2, 12 + 8 + len(js)) + struct.pack("<II", len(js), 0x4E4F534A) + js
        f = d / "o.glb"
    else:
        data, f = js, d / "o.gltf"
    f.write_bytes(data if ops is None else mutate(data, ops))
    check_reader("glTF/OBJ (io.read_object)", f, lambda: io.read_object(f), _object_valid)


# ------------------------------------------------------------------------------------------- TOML
def _verbs() -> dict[str, type]:
    import importlib

    from pipeline.run.stages import STAGES

    specs = {s.verb: s.config for s in STAGES}
    specs.update({"make-scene": "pipeline.scene.make_scene:MakeSceneConfig", "evaluate": "pipeline.measure.evaluate:EvaluateConfig",
                  "run": "pipeline.run.stages:RunConfig", "import": "pipeline.ingest.import_scan:ImportConfig"})
    out = {}
    for verb, spec in specs.items():
        m, _, c = spec.partition(":")
        out[verb] = getattr(importlib.import_module(m), c)
    return out


TOML_SCALARS = st.one_of(st.integers(-2 ** 40, 2 ** 40), st.sampled_from(["nan", "inf", "-inf", "0.0", "-1.0", "1e308", "1.5", "0.5",
                                                                         '"x"', '""', "true", "false", "[]", "[1, 2, 3]",
                                                                         "[0.5, 0.5, 2.0]", '["a"]', "{}", "1979-05-27",
                                                                         "[[1, 2, 3]]", '"1,2,3"']))


@st.composite
def toml_files(draw) -> tuple[str, str]:
    verbs = _verbs()
    verb = draw(st.sampled_from(sorted(verbs)))
    fields = [f.replace("_", draw(st.sampled_from(["_", "-"]))) for f in verbs[verb].field_names()]
    lines = []
    if draw(st.booleans()):
        lines.append(f"seed = {draw(TOML_SCALARS)}")
    if draw(st.integers(0, 4)) == 0:
        lines.append(f"{draw(st.sampled_from(fields + ['stray']))} = {draw(TOML_SCALARS)}")
    for table in draw(st.lists(st.sampled_from(sorted(verbs) + ["nope", "seed"]), max_size=3, unique=True)) + [verb]:
        lines.append(f"[{table}]")
        for _ in range(draw(st.integers(0, 4))):
            lines.append(f"{draw(st.sampled_from(fields + ['sizee']))} = {draw(TOML_SCALARS)}")
    text = ("\n".join(lines) + "\n").encode()
    if draw(st.integers(0, 5)) == 0:
        text = mutate(text, draw(OPS))  # raw bytes: not always UTF-8
    return verb, text


@SETTINGS
@given(case=toml_files())
@example(case=("relight", b"[relight]\nalbedo = [0.5, 0.5, 2.0]\n"))
@example(case=("build-bsh", b"tc = 0.5\n[build-bsh]\n"))
@example(case=("relight", b"seed = 1\n[relight]\nfov = 4\x9a.0\n"))  # found by atheris: UnicodeDecodeError from tomllib
def test_toml_config(tmp_path_factory, case):
    from pipeline.config import resolve

    verb, text = case
    f = tmp_path_factory.mktemp("toml") / "c.toml"
    f.write_bytes(text)
    cls = _verbs()[verb]

    def valid(cfg) -> None:
        cfg.check()
        cfg.check_physical()  # nothing impossible got through

    check_reader("TOML (config.resolve)", f, lambda: resolve(cls, f, verb, {}), valid)


# ------------------------------------------------------------------------------------------- scene.json
SCENE_PATHS = [("views", "view1", "eye"), ("views", "view1", "target"), ("views", "view1", "up"), ("views", "view1", "fov_deg"),
               ("views", "view1", "size"), ("views", "view1"), ("views",), ("object", "file"), ("object", "to_world"),
               ("object", "radius"), ("object",), ("meshes", 0, "albedo"), ("materials", "ggx0.1", "roughness"),
               ("sun", "radiance"), ("lamps", "radius")]
SCENE_VALS = st.one_of(JSON_VALS, st.lists(st.integers(-3, 5000), min_size=2, max_size=2),
                       st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=3, max_size=3),
                       st.just([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1]]), st.just("object.glb"))


@SETTINGS
@given(edits=st.lists(st.tuples(st.sampled_from(SCENE_PATHS), SCENE_VALS), min_size=1, max_size=3),
       ops=st.one_of(st.none(), OPS))
@example(edits=[(("views", "view1", "fov_deg"), 0)], ops=None)
@example(edits=[(("views", "view1", "size"), [0, 128])], ops=None)
def test_scene_json(tmp_path_factory, edits, ops):
    from pipeline.relight.relight import RelightConfig
    from pipeline.relight.inputs import camera_for

    doc = json.loads((SAMPLES / "scene.json").read_text())
    for path, value in edits:
        try:
            _set(doc, path, value)
        except (KeyError, IndexError, TypeError):
            pass
    f = tmp_path_factory.mktemp("scene") / "scene.json"
    data = json.dumps(doc).encode()
    f.write_bytes(data if ops is None else mutate(data, ops))

    def read_and_place():
        scene = io.read_json(f)
        cam = camera_for(RelightConfig(), scene, f, "view1")
        return scene, cam

    def valid(res) -> None:
        scene, cam = res
        assert cam.size[0] >= 1 and cam.size[1] >= 1 and 0 < cam.fov_deg < 180
        with np.errstate(all="ignore"):
            assert np.all(np.isfinite(cam.view_matrix())) and np.all(np.isfinite(cam.proj_matrix(0.01, 100.0)))
        tw = (scene.get("object") or {}).get("to_world")
        if tw is not None:
            assert abs(np.linalg.det(np.asarray(tw, float)[:3, :3])) > 0

    check_reader("scene.json (io.read_json + relight camera)", f, read_and_place, valid)


# ------------------------------------------------------------------------------------------- scans (pcrelight import)
def _scan_seed(ext: str, d: Path) -> bytes:
    rng = np.random.default_rng(4)
    p = rng.uniform(-2, 2, (12, 3))
    c = rng.integers(0, 256, (12, 3))
    if ext == "xyzrgb":
        return "".join(f"{a:.4f} {b:.4f} {z:.4f} {r / 255:.4f} {g / 255:.4f} {bb / 255:.4f}\n"
                       for (a, b, z), (r, g, bb) in zip(p, c)).encode()
    if ext == "pts":
        return (f"{len(p)}\n" + "".join(f"{a:.4f} {b:.4f} {z:.4f} 0 {r} {g} {bb}\n" for (a, b, z), (r, g, bb) in zip(p, c))).encode()
    if ext == "pcd":
        head = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U\nCOUNT 1 1 1 1\n"
                f"WIDTH {len(p)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(p)}\nDATA ascii\n")
        return (head + "".join(f"{a:.4f} {b:.4f} {z:.4f} {(int(r) << 16) | (int(g) << 8) | int(bb)}\n"
                               for (a, b, z), (r, g, bb) in zip(p, c))).encode()
    f = d / "seed.ply"
    io.write_cloud(f, io.Cloud(p.astype(np.float32), (p / np.linalg.norm(p, axis=1, keepdims=True)).astype(np.float32),
                               (c / 255).astype(np.float32)), uchar_colors=True)
    return f.read_bytes()


def _scan_valid(sc) -> None:
    assert len(sc.points) > 0 and sc.points.shape == (len(sc.points), 3) and sc.colors.shape == sc.points.shape
    assert np.all(np.isfinite(sc.colors)) and np.all(sc.colors >= 0)
    if sc.normals is not None:
        assert sc.normals.shape == sc.points.shape


def _scan_case(tmp_path_factory, ext, ops) -> None:
    from pipeline.io import read_scan

    d = tmp_path_factory.mktemp("scan")
    f = d / f"scan.{ext}"
    f.write_bytes(mutate(_scan_seed(ext, d), ops) if ops else _scan_seed(ext, d))
    check_reader("scans (io.read_scan)", f, lambda: read_scan(f), _scan_valid)


@SETTINGS
@given(ext=st.sampled_from(["xyzrgb", "pts", "ply"]), ops=st.one_of(st.just([]), OPS))
def test_scan_reader_mutated(tmp_path_factory, ext, ops):
    """``pcrelight import``'s readers (issue 24: PLY through io.read_cloud, XYZRGB/PTS through Open3D)
    on mutated scans: a Scan with finite, non-negative colours or one clean line."""
    _scan_case(tmp_path_factory, ext, ops)


# found by make fuzz (fixed in io.check_pcd_header): a PCD cut inside its header (no COUNT/WIDTH/POINTS/DATA
# lines) made Open3D's read_point_cloud size its arrays from uninitialised values: std::bad_alloc (MemoryError) under
# the 6 GiB cap, else a 1-point cloud of garbage that import wrote


@SETTINGS
@given(ops=st.one_of(st.just([]), OPS))
@example(ops=[(1, 66, 0)])  # found by fuzzing: the header cut after TYPE
def test_pcd_reader_mutated(tmp_path_factory, ops):
    """The same for PCD (Open3D)."""
    _scan_case(tmp_path_factory, "pcd", ops)


def test_pcd_header_without_data_is_refused(tmp_path):
    """Regression of the crash above: the seed PCD cut after its TYPE line is one clean line, not a point."""
    from pipeline.errors import InputError as _InputError
    from pipeline.io import read_scan

    f = tmp_path / "scan.pcd"
    f.write_bytes(b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U")
    with pytest.raises(_InputError, match="scan.pcd"):
        read_scan(f)


# ------------------------------------------------------------------------------------------- 3DGS PLY
def _gs_seed(tmp: Path, n_rest: int) -> bytes:
    rng = np.random.default_rng(3)
    n = 8
    q = rng.normal(size=(n, 4))
    f = tmp / "seed_gs.ply"
    io.write_gaussian_splats(f, rng.uniform(-2, 2, (n, 3)), rng.uniform(0.01, 0.1, (n, 3)),
                             q / np.linalg.norm(q, axis=1, keepdims=True), rng.uniform(0.2, 1.0, n),
                             rng.uniform(0, 1, (n, 3)), n_rest=n_rest)
    return f.read_bytes()


GS_PROPS = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "f_rest_0", "opacity", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3", "nx"]


@st.composite
def gs_files(draw) -> bytes:
    """A 3DGS PLY written from scratch: f_dc_0 always (what marks a splat file), a random subset and order of the
    other properties, ASCII numbers (NaN, Inf, zero quaternions, huge scales) or binary bytes, a count that may lie."""
    props = ["f_dc_0"] + draw(st.lists(st.sampled_from(GS_PROPS), min_size=0, max_size=16))
    fmt = draw(st.sampled_from(["ascii", "binary_little_endian"]))
    n_decl = draw(st.sampled_from([0, 1, 2, 4, 40, 2 ** 31]))
    n_rows = draw(st.integers(0, 5))
    head = f"ply\nformat {fmt} 1.0\nelement vertex {n_decl}\n" + "".join(f"property float {p}\n" for p in props)
    head += "end_header\n"
    if fmt == "ascii":
        body = ("\n".join(" ".join(str(draw(NUMS)) for _ in props) for _ in range(n_rows)) + "\n").encode()
    else:
        body = draw(st.binary(max_size=400))
    return head.encode() + body


def _gs_valid(sc) -> None:
    _scan_valid(sc)
    assert sc.normals is not None and np.all(np.abs(np.linalg.norm(sc.normals, axis=1) - 1) < 1e-3)
    assert np.all(sc.colors <= 1.0)


@SETTINGS
@given(data=gs_files())
def test_gaussian_splat_reader_generated(tmp_path_factory, data):
    """Issue 47: ``import`` of a 3DGS PLY (io.read_scan → read_gaussian_splats) on generated files: a scan of unit
    normals and colours in [0, 1], or one clean line (missing property, NaN, zero quaternion, a lying count)."""
    from pipeline.io import read_scan

    d = tmp_path_factory.mktemp("gs")
    f = d / "splats.ply"
    f.write_bytes(data)
    check_reader("3DGS (io.read_gaussian_splats)", f, lambda: read_scan(f), _gs_valid)


@SETTINGS
@given(n_rest=st.sampled_from([0, 9, 45]), ops=st.one_of(st.just([]), OPS))
def test_gaussian_splat_reader_mutated(tmp_path_factory, n_rest, ops):
    """The same on mutated files of the reference trainer's layout (io.write_gaussian_splats)."""
    from pipeline.io import read_scan

    d = tmp_path_factory.mktemp("gsm")
    f = d / "splats.ply"
    seed = _gs_seed(d, n_rest)
    f.write_bytes(mutate(seed, ops) if ops else seed)
    check_reader("3DGS (io.read_gaussian_splats)", f, lambda: read_scan(f), _gs_valid)


def test_counts_cover_every_reader():
    """Runs last in this module: every reader was tried (and, under make fuzz, as often as asked)."""
    readers = ["PLY (io.read_cloud)", "EXR/HDR/PNG (io.read_image)", "NPZ (io.read_npz)", "glTF/OBJ (io.read_object)",
               "TOML (config.resolve)", "scene.json (io.read_json + relight camera)", "scans (io.read_scan)",
               "3DGS (io.read_gaussian_splats)"]
    if not all(r in COUNTS for r in readers):
        pytest.skip("run with the whole module to count inputs per reader")
    for r in readers:
        assert COUNTS[r]["inputs"] >= FUZZ_EXAMPLES, (r, COUNTS[r])
