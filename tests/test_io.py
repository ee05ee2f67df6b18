"""Round trips and error cases of pipeline/io.py (the stage-file contracts)."""

from __future__ import annotations

import numpy as np
import pytest

from object_parts import assert_same_parts
from pipeline import io
from pipeline.errors import InputError
from pipeline.schemas import register


def _cloud(n=200, seed=0, lo=-6.0, hi=6.0):
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
    nrm = rng.normal(size=(n, 3))
    nrm = (nrm / np.linalg.norm(nrm, axis=1, keepdims=True)).astype(np.float32)
    col = (10.0 ** rng.uniform(lo, hi, (n, 3))).astype(np.float32)
    return io.Cloud(pts, nrm, col)


def test_ply_float_hdr_roundtrip_is_exact(tmp_path):
    c = _cloud()
    c.colors[0] = (1e-6, 1.0, 1e6)
    c.valid = (np.arange(len(c)) % 2).astype(np.uint8)
    c.quality = np.linspace(0, 5, len(c), dtype=np.float32)
    c.source = (np.arange(len(c)) % 3).astype(np.uint8)
    io.write_cloud(tmp_path / "c.ply", c)
    r = io.read_cloud(tmp_path / "c.ply")
    assert r.colors.dtype == np.float32
    assert np.array_equal(r.colors, c.colors)  # bit-exact, 1e-6 … 1e6
    assert np.array_equal(r.points, c.points)
    np.testing.assert_allclose(r.normals, c.normals, atol=1e-6)
    for k in ("valid", "quality", "source"):
        assert np.array_equal(getattr(r, k), getattr(c, k))
    head = (tmp_path / "c.ply").read_bytes()[:400]
    assert b"binary_little_endian" in head and b"property float red" in head


def test_ply_uchar_colours_are_srgb_decoded_with_colour_science(tmp_path):
    import colour
    from plyfile import PlyData, PlyElement

    v = np.zeros(256, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("nx", "f4"), ("ny", "f4"), ("nz", "f4"),
                             ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    v["x"] = np.arange(256)
    v["ny"] = 1
    v["red"] = np.arange(256)
    v["green"] = 255 - np.arange(256)
    v["blue"] = 128
    PlyData([PlyElement.describe(v, "vertex")]).write(str(tmp_path / "u.ply"))
    r = io.read_cloud(tmp_path / "u.ply")
    expect = colour.models.eotf_sRGB(np.arange(256) / 255.0)
    np.testing.assert_allclose(r.colors[:, 0], expect, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(r.colors[:, 1], expect[::-1], rtol=1e-6, atol=1e-7)
    # and writing uchar encodes back to the same bytes
    io.write_cloud(tmp_path / "u2.ply", r, uchar_colors=True)
    back = PlyData.read(str(tmp_path / "u2.ply"))["vertex"].data
    assert np.array_equal(back["red"], v["red"]) and np.array_equal(back["green"], v["green"])


def test_ascii_ply_and_missing_normals_are_estimated(tmp_path):
    # points on the plane y = 0: normals must be ±Y, unit length; oriented to the centroid side
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(-1, 1, 300), np.zeros(300), rng.uniform(-1, 1, 300)]
    pts = np.r_[pts, [[0, 1.0, 0]]]  # one point above lifts the centroid to y > 0
    lines = ["ply", "format ascii 1.0", f"element vertex {len(pts)}", "property float x", "property float y",
             "property float z", "property float red", "property float green", "property float blue", "end_header"]
    lines += [f"{x} {y} {z} 0.5 2.0 0.25" for x, y, z in pts]
    (tmp_path / "a.ply").write_text("\n".join(lines) + "\n")
    r = io.read_cloud(tmp_path / "a.ply")
    np.testing.assert_allclose(np.linalg.norm(r.normals, axis=1), 1.0, atol=1e-5)
    assert np.all(r.normals[:300, 1] > 0.99)  # +Y: towards the centroid (y > 0)
    np.testing.assert_allclose(r.colors[0], [0.5, 2.0, 0.25])


def _write_raw_ply(path, n, fields, rows):
    header = ["ply", "format ascii 1.0", f"element vertex {n}"] + [f"property float {f}" for f in fields] + ["end_header"]
    path.write_text("\n".join(header + [" ".join(map(str, r)) for r in rows]) + "\n")


@pytest.mark.parametrize("case,needle", [
    ("missing", "no such file"),
    ("empty", "empty point cloud"),
    ("nan_colour", "non-finite colors"),
    ("inf_position", "non-finite positions"),
    ("no_colour", "no colours"),
    ("zero_normal", "zero-length normals"),
    ("truncated", "not a readable PLY"),
    ("garbage", "not a readable PLY"),
])
def test_bad_clouds_give_one_line_naming_the_file(tmp_path, case, needle):
    p = tmp_path / f"{case}.ply"
    full = ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"]
    if case == "empty":
        _write_raw_ply(p, 0, full, [])
    elif case == "nan_colour":
        _write_raw_ply(p, 2, full, [[0, 0, 0, 0, 1, 0, 1, 1, 1], [1, 0, 0, 0, 1, 0, "nan", 1, 1]])
    elif case == "inf_position":
        _write_raw_ply(p, 2, full, [[0, 0, 0, 0, 1, 0, 1, 1, 1], ["inf", 0, 0, 0, 1, 0, 1, 1, 1]])
    elif case == "no_colour":
        _write_raw_ply(p, 1, full[:6], [[0, 0, 0, 0, 1, 0]])
    elif case == "zero_normal":
        _write_raw_ply(p, 2, full, [[0, 0, 0, 0, 1, 0, 1, 1, 1], [1, 0, 0, 0, 0, 0, 1, 1, 1]])
    elif case == "truncated":
        io.write_cloud(p, _cloud(100))
        data = p.read_bytes()
        p.write_bytes(data[: len(data) - 500])
    elif case == "garbage":
        p.write_bytes(b"\x00\x01garbage" * 10)
    with pytest.raises(InputError) as e:
        io.read_cloud(p)
    msg = str(e.value)
    assert "\n" not in msg and str(p) in msg and needle in msg


def test_colour_count_mismatch_is_an_error(tmp_path):
    c = _cloud(10)
    c.colors = c.colors[:9]
    with pytest.raises(InputError, match="colors count 9 != point count 10"):
        io.write_cloud(tmp_path / "x.ply", c)
    assert not (tmp_path / "x.ply").exists()


@pytest.mark.parametrize("half,channels", [(False, 1), (False, 3), (False, 4), (True, 4), (False, 5)])
def test_exr_roundtrip(tmp_path, half, channels):
    rng = np.random.default_rng(2)
    img = (10.0 ** rng.uniform(-4, 4 if half else 8, (7, 9, channels))).astype(np.float32)
    io.write_image(tmp_path / "i.exr", img, half=half)
    back = io.read_image(tmp_path / "i.exr")
    assert back.shape == img.shape
    if half:
        np.testing.assert_allclose(back, img.astype(np.float16).astype(np.float32), rtol=0, atol=0)
    else:
        assert np.array_equal(back, img)
    names = io.image_channels(tmp_path / "i.exr")
    assert names[: min(channels, 4)] == {1: ["Y"], 3: ["R", "G", "B"]}.get(channels, ["R", "G", "B", "A"])[: min(channels, 4)]


def test_half_overflow_is_refused(tmp_path):
    with pytest.raises(ValueError, match="65504"):
        io.write_image(tmp_path / "h.exr", np.full((2, 2, 3), 1e5, np.float32), half=True)


def test_radiance_hdr_roundtrip_within_rgbe_precision(tmp_path):
    rng = np.random.default_rng(3)
    img = (10.0 ** rng.uniform(-2, 4, (5, 6, 3))).astype(np.float32)
    io.write_image(tmp_path / "i.hdr", img)
    back = io.read_image(tmp_path / "i.hdr")
    # RGBE keeps 8 mantissa bits of the largest channel: relative error ≤ 2^-8 of the max channel
    err = np.abs(back - img) / img.max(axis=2, keepdims=True)
    assert err.max() < 2.0 ** -7


def test_corrupt_exr(tmp_path):
    io.write_image(tmp_path / "ok.exr", np.ones((64, 64, 3), np.float32))
    data = (tmp_path / "ok.exr").read_bytes()
    (tmp_path / "bad.exr").write_bytes(data[: len(data) // 3])
    with pytest.raises(InputError) as e:
        io.read_image(tmp_path / "bad.exr")
    assert str(tmp_path / "bad.exr") in str(e.value) and "\n" not in str(e.value)


def _exr_as_stored(path, img, fmt):
    """Write ``img`` through OpenImageIO as is (io.write_image refuses half overflow; a foreign writer does not)."""
    import OpenImageIO as oiio

    h, w, c = img.shape
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(w, h, c, fmt)), out.geterror()
    assert out.write_image(img), out.geterror()
    out.close()


@pytest.mark.parametrize("fmt,value,kind", [("float", np.nan, "NaN"), ("float", np.inf, "Inf"), ("float", -np.inf, "Inf"),
                                            ("half", np.inf, "Inf"), ("half", np.nan, "NaN")])
def test_non_finite_pixels_are_bad_input(tmp_path, fmt, value, kind):
    """Issue 30: an image holding NaN or ±Inf is refused with one line naming the file, how many pixels
    and where the first one is (no stage means them; they would spread through every sum)."""
    img = np.ones((4, 5, 3), np.float32)
    img[1, 2, 0] = value
    img[3, 4, 2] = value
    _exr_as_stored(tmp_path / "p.exr", img, fmt)
    with pytest.raises(InputError) as e:
        io.read_image(tmp_path / "p.exr")
    msg = str(e.value)
    assert msg == f"{tmp_path / 'p.exr'}: 2 of 5×4 pixels hold non-finite values ({kind}; the first at x=2, y=1)", msg


def test_radiance_hdr_cannot_carry_non_finite_values(tmp_path):
    """The .hdr path: RGBE has no NaN/Inf code; NaN/Inf written are stored as 0, and the largest
    RGBE value (exponent byte 255) reads back finite (about 1.69e38), so read_image's finiteness
    check has nothing to refuse there."""
    f = tmp_path / "x.hdr"
    f.write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 1 +X 2\n" + bytes([255, 255, 255, 255, 128, 128, 128, 129]))
    a = io.read_image(f)
    assert a.shape == (1, 2, 3) and np.all(np.isfinite(a))
    assert a[0, 0].min() > 1e38 and np.array_equal(a[0, 1], [1, 1, 1])
    img = np.ones((2, 3, 3), np.float32)
    img[0, 1] = [np.nan, np.inf, 1.0]
    io.write_image(tmp_path / "w.hdr", img)
    b = io.read_image(tmp_path / "w.hdr")
    assert np.all(np.isfinite(b)) and np.array_equal(b[1], img[1])


def test_preview_png(tmp_path):
    img = np.zeros((16, 16, 4), np.float32)
    img[4:12, 4:12, :3] = 1e5
    img[4:12, 4:12, 3] = 1
    io.write_preview(tmp_path / "p.png", img)
    back = io.read_image(tmp_path / "p.png")
    assert back.shape == (16, 16, 4)
    assert back[8, 8, :3].min() > 0.3 and back[0, 0, 3] == 0 and back[8, 8, 3] == 1


register("pcrelight.test/1", {"a": ("float32", ("N", 3)), "b": ("int32", ("N",)), "name": ("str", ()),
                              "opt": ("uint8", (None,), "optional")})


def test_npz_roundtrip_is_validated_and_deterministic(tmp_path):
    a = np.arange(12, dtype=np.float32).reshape(4, 3)
    b = np.arange(4, dtype=np.int32)
    io.write_npz(tmp_path / "x.npz", "pcrelight.test/1", a=a, b=b, name=np.asarray("hi"))
    io.write_npz(tmp_path / "y.npz", "pcrelight.test/1", a=a, b=b, name=np.asarray("hi"))
    assert (tmp_path / "x.npz").read_bytes() == (tmp_path / "y.npz").read_bytes()
    d = io.read_npz(tmp_path / "x.npz", "pcrelight.test/1")
    assert np.array_equal(d["a"], a) and str(d["name"]) == "hi" and "opt" not in d


@pytest.mark.parametrize("arrays,needle", [
    (dict(a=np.zeros((4, 3), np.float64), b=np.zeros(4, np.int32), name=np.asarray("x")), "dtype float64"),
    (dict(a=np.zeros((4, 2), np.float32), b=np.zeros(4, np.int32), name=np.asarray("x")), "shape"),
    (dict(a=np.zeros((4, 3), np.float32), b=np.zeros(5, np.int32), name=np.asarray("x")), "N=5"),
    (dict(a=np.zeros((4, 3), np.float32), name=np.asarray("x")), "missing key 'b'"),
])
def test_npz_schema_errors(tmp_path, arrays, needle):
    import zipfile

    p = tmp_path / "bad.npz"
    np.savez(p, schema=np.asarray("pcrelight.test/1"), **arrays)
    with pytest.raises(InputError) as e:
        io.read_npz(p, "pcrelight.test/1")
    assert needle in str(e.value) and str(p) in str(e.value)
    assert zipfile.is_zipfile(p)


def test_npz_wrong_or_missing_schema(tmp_path):
    np.savez(tmp_path / "w.npz", schema=np.asarray("pcrelight.other/1"))
    np.savez(tmp_path / "m.npz", a=np.zeros(3))
    with pytest.raises(InputError, match="schema is 'pcrelight.other/1', expected 'pcrelight.test/1'"):
        io.read_npz(tmp_path / "w.npz", "pcrelight.test/1")
    with pytest.raises(InputError, match="no 'schema' key"):
        io.read_npz(tmp_path / "m.npz", "pcrelight.test/1")
    (tmp_path / "c.npz").write_bytes(b"PK\x03\x04broken")
    with pytest.raises(InputError, match="not a readable NPZ"):
        io.read_npz(tmp_path / "c.npz", "pcrelight.test/1")


def test_atomic_write_keeps_old_file_when_interrupted(tmp_path):
    p = tmp_path / "c.ply"
    io.write_cloud(p, _cloud(50))
    before = p.read_bytes()

    class Boom(Exception):
        pass

    with pytest.raises(Boom):
        with io.atomic_path(p) as tmp:
            tmp.write_bytes(b"half-written")
            raise Boom()
    assert p.read_bytes() == before
    assert sorted(x.name for x in tmp_path.iterdir()) == ["c.ply"]  # no temp file left


def test_luminance_matches_rec709_weights():
    y = io.luminance(np.eye(3, dtype=np.float32))
    np.testing.assert_allclose(y, [0.2126, 0.7152, 0.0722], atol=1e-4)


def test_a_radiance_hdr_copy_of_the_sample_photo_reads_to_its_pixels(tmp_path):
    """Issue 24: users bring .hdr photos. The shipped photo.exr (256×384, up to 45) written as RGBE and read
    back: every pixel within 2^-7 of its largest channel (measured 0.0078), the mean 0.36 % low (OIIO's RGBE
    writer truncates the mantissa)."""
    from pathlib import Path

    exr = io.read_image(Path(__file__).resolve().parents[1] / "data_samples" / "photo.exr")[:, :, :3]
    io.write_image(tmp_path / "photo.hdr", exr)
    hdr = io.read_image(tmp_path / "photo.hdr")
    assert hdr.shape == exr.shape and hdr.dtype == np.float32
    err = np.abs(hdr - exr) / exr.max(axis=2, keepdims=True)
    assert err.max() <= 2.0 ** -7 * 1.001, err.max()
    assert 0.995 < hdr.mean() / exr.mean() <= 1.0


def test_read_object_cache_gives_the_parts_without_trimesh(tmp_path, monkeypatch):
    """read_object(cache=True): a GLB or PLY is parsed once; the next read gives the same parts (every key, value
    type and array byte) from the cache folder, in a fresh process without importing trimesh; an OBJ (its MTL and
    textures are other files) is not cached."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    from pipeline.io.cache import CACHE_ENV

    cache = tmp_path / "cache"
    monkeypatch.setenv(CACHE_ENV, str(cache))
    rng = np.random.default_rng(0)
    v = rng.normal(size=(30, 3)).astype(np.float32)
    f = rng.integers(0, 30, (40, 3))
    n = v / np.linalg.norm(v, axis=1, keepdims=True)
    for ext in ("glb", "ply", "obj"):
        p = tmp_path / f"o.{ext}"
        io.write_mesh(p, v, f, n, **({"base_color": (0.2, 0.4, 0.6), "metallic": 0.3, "roughness": 0.7}
                                     if ext == "glb" else {}))
        want = io.read_object(p)
        for _ in range(2):
            assert_same_parts(io.read_object(p, cache=True), want)
    assert len(list((cache / "object").glob("*.npz"))) == 2          # the GLB's and the PLY's
    code = ("import sys; from pipeline import io; parts = io.read_object(sys.argv[1], cache=True); "
            "print(len(parts), 'trimesh' in sys.modules)")
    root = str(Path(__file__).resolve().parents[1])
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path / "o.glb")], capture_output=True, text=True,
                       cwd=root, env={**os.environ, "PYTHONPATH": root})
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["1", "False"]
