"""pcrelight import (issue 24): copies of data_samples/cloud_ldr.ply in other units, axes and formats import
to the same cloud as the PLY; outliers 50 m away are removed and change nothing else; --max-points; a bad
file is one line, exit 1, nothing written; the output is byte-deterministic."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline import io
from pipeline.ingest.import_scan import ROTATIONS

SAMPLE = Path(__file__).resolve().parents[1] / "data_samples" / "cloud_ldr.ply"
TO_ZUP = ROTATIONS["z"].T          # +Y up → +Z up (the inverse of what import applies)


@pytest.fixture(scope="module")
def sample():
    return io.read_cloud(SAMPLE)


@pytest.fixture(scope="module")
def sample_u8():
    """The sample's stored 8-bit sRGB colours (what a scanner's file holds)."""
    from plyfile import PlyData

    v = PlyData.read(str(SAMPLE))["vertex"].data
    return np.stack([v["red"], v["green"], v["blue"]], axis=1)


def _import(tmp: Path, src: Path, *args: str, name: str = "out.ply"):
    from click.testing import CliRunner

    import cli

    out = tmp / name
    r = CliRunner().invoke(cli.main, ["import", str(src), "--out", str(out), "-q", *args], catch_exceptions=False)
    rep = json.loads(out.with_suffix(".json").read_text()) if r.exit_code == 0 else None
    return r.exit_code, r.stderr, out, rep


@pytest.fixture(scope="module")
def reference(tmp_path_factory, sample):
    tmp = tmp_path_factory.mktemp("ref")
    code, err, out, rep = _import(tmp, SAMPLE)
    assert code == 0, err
    return io.read_cloud(out), out, rep


def _write_ply_copy(path: Path, pts: np.ndarray, nrm: np.ndarray | None, u8: np.ndarray) -> None:
    from plyfile import PlyData, PlyElement

    fields = [(c, "<f4") for c in "xyz"] + ([("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")] if nrm is not None else [])
    arr = np.empty(len(pts), dtype=fields + [("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for i, c in enumerate("xyz"):
        arr[c] = pts[:, i]
        if nrm is not None:
            arr["n" + c] = nrm[:, i]
    for i, c in enumerate(("red", "green", "blue")):
        arr[c] = u8[:, i]
    PlyData([PlyElement.describe(arr, "vertex")], byte_order="<").write(str(path))


def _same(got, want, normals: bool = True, col_tol: float = 0.0) -> tuple[float, float]:
    """Same points (to 1e-5 m) in the same order, same colours (to col_tol); returns the largest differences."""
    assert len(got) == len(want)
    dp = float(np.abs(got.points.astype(np.float64) - want.points).max())
    dc = float(np.abs(got.colors.astype(np.float64) - want.colors).max())
    assert dp <= 1e-5, dp
    assert dc <= col_tol, dc
    if normals:
        assert float(np.abs(got.normals - want.normals).max()) <= 1e-5
    return dp, dc


# --------------------------------------------------------------------------- the reference
def test_the_sample_imports_to_itself(reference, sample):
    cloud, _, rep = reference
    assert _same(cloud, sample) == (0.0, 0.0)
    assert rep["units"]["unit"] == "m" and abs(rep["units"]["size"] - 21.60) < 0.01    # 30 × 24 × 14 m
    assert rep["up"]["up"] == "y" and rep["up"]["scores"]["y"] == 27448 and rep["up"]["runner_up"] == "z"
    assert rep["outliers"]["removed"] == 0 and rep["normals"] == "given" and rep["downsample"] is None


# --------------------------------------------------------------------------- other units and axes
@pytest.mark.parametrize("unit,scale", [("cm", 100.0), ("mm", 1000.0)])
def test_a_copy_in_other_units_imports_to_the_same_cloud(tmp_path, reference, sample, sample_u8, unit, scale):
    src = tmp_path / f"room_{unit}.ply"
    _write_ply_copy(src, (sample.points.astype(np.float64) * scale).astype(np.float32), sample.normals, sample_u8)
    code, err, out, rep = _import(tmp_path, src)
    assert code == 0, err
    assert rep["units"]["unit"] == unit and rep["units"]["by"].startswith("detected")
    dp, dc = _same(io.read_cloud(out), reference[0])
    assert dc == 0.0 and dp < 3e-6  # float32 of the scaled coordinates, divided back


@pytest.mark.parametrize("normals", [True, False], ids=["normals", "no-normals"])
def test_a_z_up_copy_imports_to_the_same_cloud(tmp_path, reference, sample, sample_u8, normals):
    src = tmp_path / "room_zup.ply"
    _write_ply_copy(src, sample.points @ TO_ZUP.T.astype(np.float32),
                    (sample.normals @ TO_ZUP.T.astype(np.float32)) if normals else None, sample_u8)
    code, err, out, rep = _import(tmp_path, src)
    assert code == 0, err
    assert rep["up"]["up"] == "z" and rep["up"]["by"].startswith("detected")
    got = io.read_cloud(out)
    assert _same(got, reference[0], normals=normals) == (0.0, 0.0)  # a permutation and a sign: exact
    if not normals:  # estimated (k-NN PCA towards the centroid): the floor still decides, from these
        assert rep["normals"].startswith("estimated")
        agree = np.abs(np.sum(got.normals * reference[0].normals, axis=1)) > 0.9
        assert agree.mean() > 0.85, agree.mean()  # 0.906 measured: edges and corners differ


def test_units_and_up_can_be_given(tmp_path, reference, sample, sample_u8):
    src = tmp_path / "room_cm_zup.ply"
    _write_ply_copy(src, ((sample.points.astype(np.float64) @ TO_ZUP.T) * 100.0).astype(np.float32),
                    sample.normals @ TO_ZUP.T.astype(np.float32), sample_u8)
    code, err, out, rep = _import(tmp_path, src, "--units", "cm", "--up", "z")
    assert code == 0, err
    assert rep["units"]["by"] == "given (--units)" and rep["up"]["by"] == "given (--up)"
    _same(io.read_cloud(out), reference[0])
    code, err, out, rep = _import(tmp_path, src, "--units", "m", name="wrong.ply")  # the user is believed
    assert code == 0 and rep["units"]["unit"] == "m"


# --------------------------------------------------------------------------- other formats
def test_an_e57_copy_imports_to_the_same_cloud(tmp_path, reference, sample, sample_u8):
    pye57 = pytest.importorskip("pye57")
    zup = sample.points.astype(np.float64) @ TO_ZUP.T   # E57 files are Z-up metres
    src = tmp_path / "room.e57"
    e = pye57.E57(str(src), mode="w")
    e.write_scan_raw({"cartesianX": zup[:, 0], "cartesianY": zup[:, 1], "cartesianZ": zup[:, 2],
                      "colorRed": sample_u8[:, 0], "colorGreen": sample_u8[:, 1], "colorBlue": sample_u8[:, 2]})
    e.close()
    code, err, out, rep = _import(tmp_path, src)
    assert code == 0, err
    assert rep["units"]["by"].startswith("E57 stores metres") and rep["up"]["up"] == "z"
    assert rep["read"]["scans"][0]["colour_max"] == 255.0 and rep["normals"].startswith("estimated")
    got = io.read_cloud(out)
    dp, dc = _same(got, reference[0], normals=False)
    assert dc == 0.0 and dp < 2e-6  # libE57 stores the coordinates as float32 here
    assert np.mean(np.abs(np.sum(got.normals * reference[0].normals, axis=1)) > 0.9) > 0.85


@pytest.mark.parametrize("suffix", ["las", "laz"])
def test_a_las_copy_imports_to_the_same_cloud(tmp_path, reference, sample, sample_u8, suffix):
    laspy = pytest.importorskip("laspy")
    if suffix == "laz":
        pytest.importorskip("lazrs")
    zup = sample.points.astype(np.float64) @ TO_ZUP.T
    hdr = laspy.LasHeader(point_format=2, version="1.2")
    hdr.scales = np.array([1e-6, 1e-6, 1e-6])   # LAS stores integers: 1 µm steps (1 mm is the common default)
    hdr.offsets = np.zeros(3)
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = zup[:, 0], zup[:, 1], zup[:, 2]
    rgb16 = sample_u8.astype(np.uint16) * 257     # 8-bit → the full 16-bit range
    las.red, las.green, las.blue = rgb16[:, 0], rgb16[:, 1], rgb16[:, 2]
    src = tmp_path / f"room.{suffix}"
    las.write(str(src))
    code, err, out, rep = _import(tmp_path, src)
    assert code == 0, err
    assert rep["format"] == suffix.upper() and rep["units"]["unit"] == "m" and rep["up"]["up"] == "z"
    dp, dc = _same(io.read_cloud(out), reference[0], normals=False)
    assert dc == 0.0 and dp <= 1e-6


@pytest.mark.parametrize("fmt", ["pcd", "xyzrgb", "pts"])
def test_open3d_formats_import_to_the_same_cloud(tmp_path, reference, sample, sample_u8, fmt):
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sample.points.astype(np.float64)))
    pc.colors = o3d.utility.Vector3dVector(sample_u8.astype(np.float64) / 255.0)
    src = tmp_path / f"room.{fmt}"
    assert o3d.io.write_point_cloud(str(src), pc)
    code, err, out, rep = _import(tmp_path, src)
    assert code == 0, err
    assert rep["format"] == fmt.upper() and rep["up"]["up"] == "y" and rep["units"]["unit"] == "m"
    _same(io.read_cloud(out), reference[0], normals=False, col_tol=0.0)


# --------------------------------------------------------------------------- outliers
@pytest.mark.parametrize("kind", ["scattered", "clustered"])
def test_ten_outliers_50_m_away_are_removed_and_change_nothing_else(tmp_path, reference, sample, sample_u8, kind):
    rng = np.random.default_rng(24)
    centre = (sample.points.min(axis=0) + sample.points.max(axis=0)) / 2.0
    if kind == "scattered":  # 10 stray returns in random directions, 50 m from the room's centre
        d = rng.normal(size=(10, 3))
        far = centre + 50.0 * d / np.linalg.norm(d, axis=1, keepdims=True)
    else:                    # a ghost of 10 points within 5 cm, 50 m away: each has neighbours
        far = centre + np.array([50.0, 0.0, 0.0]) + rng.uniform(-0.05, 0.05, (10, 3))
    u8 = np.concatenate([sample_u8, np.full((10, 3), 255, np.uint8)])  # white: the bright-removal warning
    nrm = np.concatenate([sample.normals, np.tile(np.float32([0, 1, 0]), (10, 1))])
    src = tmp_path / "room_outliers.ply"
    pts = np.concatenate([sample.points, far.astype(np.float32)])
    perm = rng.permutation(len(pts))  # the outliers anywhere in the file
    _write_ply_copy(src, pts[perm], nrm[perm], u8[perm])
    code, err, out, rep = _import(tmp_path, src)
    assert code == 0, err
    o = rep["outliers"]
    assert o["removed"] == 10 and o["removed_bright"] == 10
    assert (o["isolated"], o["far"]) == ((10, 10) if kind == "scattered" else (0, 10))
    got = io.read_cloud(out)
    want = reference[0].subset(perm[perm < len(sample)])  # the sample's points, in the shuffled file's order
    assert _same(got, want) == (0.0, 0.0)
    assert rep["units"] == reference[2]["units"] and rep["up"] == reference[2]["up"]


# --------------------------------------------------------------------------- down-sampling, determinism
def test_max_points_down_samples_on_a_voxel_grid(tmp_path, reference):
    code, err, out, rep = _import(tmp_path, SAMPLE, "--max-points", "20000")
    assert code == 0, err
    got = io.read_cloud(out)
    ds = rep["downsample"]
    assert len(got) == ds["after"] <= 20000 and ds["before"] == 200000
    assert len(got) > 18000, len(got)  # bisection to 0.1 %: close to the limit
    assert 0.3 < ds["voxel_m"] < 0.45, ds["voxel_m"]  # 0.375 m measured (the sample's median spacing: 0.056 m)
    ref = reference[0]
    assert np.all(got.points.min(axis=0) >= ref.points.min(axis=0) - 1e-5)
    assert np.all(got.points.max(axis=0) <= ref.points.max(axis=0) + 1e-5)
    assert np.allclose(np.linalg.norm(got.normals, axis=1), 1.0, atol=1e-5)
    from scipy.spatial import cKDTree

    d, _ = cKDTree(ref.points).query(got.points)  # an average of a voxel's points lies in that voxel
    assert d.max() <= np.sqrt(3.0) * ds["voxel_m"], d.max()
    assert got.colors.min() >= 0.0 and got.colors.max() <= 1.0
    # the mean over voxels weights sparse regions more than the mean over points: 4.6–6.5 % apart here
    assert np.allclose(got.colors.mean(axis=0), ref.colors.mean(axis=0), rtol=0.1)


def test_the_output_is_byte_deterministic(tmp_path, sample, sample_u8):
    src = tmp_path / "room_zup_nonormals.ply"  # the most decisions: units, up, normals, down-sampling
    _write_ply_copy(src, (sample.points @ TO_ZUP.T.astype(np.float32)) * np.float32(100), None, sample_u8)
    a = _import(tmp_path, src, "--max-points", "50000", name="a.ply")
    b = _import(tmp_path, src, "--max-points", "50000", name="b.ply")
    assert a[0] == b[0] == 0, (a[1], b[1])
    assert a[2].read_bytes() == b[2].read_bytes()
    assert a[3]["units"]["unit"] == "cm" and a[3]["up"]["up"] == "z"


# --------------------------------------------------------------------------- bad input
def _bad_inputs(tmp: Path) -> dict[str, tuple[Path, str]]:
    (tmp / "garbage.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10\n")
    (tmp / "garbage.pcd").write_text("not a pcd\n")
    (tmp / "garbage.e57").write_bytes(b"\x00" * 2048)
    (tmp / "garbage.las").write_bytes(b"LASF" + b"\x00" * 100)
    (tmp / "plain.xyz").write_text("0 0 0\n1 0 0\n0 1 0\n")
    (tmp / "room.obj").write_text("v 0 0 0\n")
    (tmp / "nan.ply").write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                                 "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
                                 "end_header\nnan 0 0 1 2 3\n0 0 0 1 2 3\n")
    return {"missing": (tmp / "missing.ply", "no such file"),
            "ply": (tmp / "garbage.ply", "not a readable PLY"),
            "pcd": (tmp / "garbage.pcd", "not a readable PCD"),
            "e57": (tmp / "garbage.e57", "not a readable E57"),
            "las": (tmp / "garbage.las", "not a readable LAS"),
            "xyz": (tmp / "plain.xyz", "no colours"),
            "suffix": (tmp / "room.obj", "unknown scan format '.obj'"),
            "nan": (tmp / "nan.ply", "non-finite positions")}


@pytest.mark.parametrize("case", ["missing", "ply", "pcd", "e57", "las", "xyz", "suffix", "nan"])
def test_a_bad_file_is_one_line_exit_1_and_nothing_written(tmp_path, case):
    src, problem = _bad_inputs(tmp_path)[case]
    out = tmp_path / "out.ply"
    out.write_bytes(b"previous")
    code, err, _, _ = _import(tmp_path, src)
    assert code == 1, err
    assert err.startswith(f"pcrelight: {src}: ") and problem in err and err.count("\n") == 1, err
    assert out.read_bytes() == b"previous" and not out.with_suffix(".json").exists()
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []  # no temp file left


def test_a_missing_reader_package_is_one_line_exit_2(tmp_path, monkeypatch):
    src = tmp_path / "room.e57"
    src.write_bytes(b"\x00" * 64)
    monkeypatch.setitem(sys.modules, "pye57", None)  # import pye57 → ImportError
    code, err, _, _ = _import(tmp_path, src)
    assert code == 2 and err == f"pcrelight: {src}: reading E57 needs the Python package pye57 (pip install pye57)\n"


def test_bad_options_are_usage_errors(tmp_path):
    for args, text in ((["--max-points", "-1"], "--max-points must be ≥ 0"),
                       (["--outlier-radius", "0"], "--outlier-radius must be > 0"),
                       (["--far-margin", "-1"], "--far-margin must be ≥ 0")):
        code, err, _, _ = _import(tmp_path, SAMPLE, *args)
        assert code == 2 and text in err, err
    code, err, _, _ = _import(tmp_path, SAMPLE, name="cloud.pcd")
    assert code == 2 and "the output must be a .ply file" in err


def test_the_verb_has_the_common_options_and_its_own_with_units(tmp_path):
    from click.testing import CliRunner

    import cli

    out = CliRunner().invoke(cli.main, ["import", "--help"]).stdout
    for opt in ("--seed", "--config", "--preview", "-q", "-v", "--units", "--up", "--max-points", "[points]",
                "--outlier-radius", "spacings]", "--outlier-neighbours", "--far-margin", "[fraction]"):
        assert opt in " ".join(out.split()), opt
    assert "import" in CliRunner().invoke(cli.main, ["--help"]).stdout


def test_options_from_a_config_table_and_a_negative_up(tmp_path, reference, sample, sample_u8):
    src = tmp_path / "room_down.ply"  # upside down: -y up
    flip = np.diag([1.0, -1.0, -1.0]).astype(np.float32)
    _write_ply_copy(src, sample.points @ flip, sample.normals @ flip, sample_u8)
    toml = tmp_path / "c.toml"
    toml.write_text('[import]\nunits = "m"\n')
    code, err, out, rep = _import(tmp_path, src, "--config", str(toml), "--up", "-y", "--preview", str(tmp_path / "p.png"))
    assert code == 0, err
    assert rep["units"]["by"] == "given (--units)" and rep["up"] == {"up": "-y", "by": "given (--up)"}
    assert _same(io.read_cloud(out), reference[0]) == (0.0, 0.0) and (tmp_path / "p.png").stat().st_size > 1000
    code, err, out, rep = _import(tmp_path, src, name="auto.ply")  # and detected
    assert code == 0 and rep["up"]["up"] == "-y", err


def test_libe57_messages_do_not_reach_the_terminal(tmp_path):
    """libE57 prints its exceptions to file descriptor 2 itself: the real CLI still answers one line."""
    import subprocess

    src = tmp_path / "bad.e57"
    src.write_bytes(b"\x00" * 2048)
    r = subprocess.run([sys.executable, "-c", "import cli; cli.main()", "import", str(src), "--out", str(tmp_path / "o.ply")],
                       capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1], timeout=120)
    assert r.returncode == 1 and r.stderr.count("\n") == 1 and r.stderr.startswith(f"pcrelight: {src}: not a readable E57"), r.stderr


@pytest.mark.parametrize("header,problem", [
    (b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U", "no DATA line"),
    (b"VERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U\nDATA ascii\n", "header without WIDTH, HEIGHT, POINTS"),
    (b"FIELDS x y z rgb\nSIZE 4 4 4\nTYPE F F F U\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n0 0 0 0\n",
     "different numbers of fields"),
    (b"FIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U\nWIDTH 2\nHEIGHT 1\nPOINTS 5\nDATA ascii\n0 0 0 0\n",
     "is not WIDTH × HEIGHT"),
    (b"FIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U\nWIDTH 1000\nHEIGHT 1\nPOINTS 1000\nDATA binary\n\0\0\0\0",
     "cut short"),
    (b"FIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA zip\n", "is not one of"),
])
def test_a_pcd_header_open3d_would_misread_is_refused(tmp_path, header, problem):
    """make fuzz found that a PCD cut inside its header made Open3D size its arrays from uninitialised values
    (std::bad_alloc, or a point of garbage written out): the header is checked first, one line naming the file."""
    from pipeline.errors import InputError
    from pipeline.io import read_scan

    f = tmp_path / "scan.pcd"
    f.write_bytes(header)
    with pytest.raises(InputError, match=problem) as e:
        read_scan(f)
    assert "scan.pcd" in str(e.value)


# --------------------------------------------------------------------------- 3D Gaussian splats (issue 47)
def _write_splats(path: Path, pts: np.ndarray, nrm: np.ndarray, srgb: np.ndarray, sigma: np.ndarray,
                  opacity: np.ndarray, n_rest: int = 9, drop: str = "", nan: str = "", zero_quat: bool = False) -> None:
    """A splat PLY as the reference 3DGS trainer writes it: f_dc from sRGB colours (their inverse DC map), ln σ for
    two tangent axes and the normal's (axis 2, the shortest), the quaternion (w, x, y, z) taking +z to the normal
    (stored un-normalised, × 2.5, as trainers leave them), opacity as a logit, ``n_rest`` f_rest coefficients."""
    from plyfile import PlyData, PlyElement

    from pipeline.io.clouds import GS_PROPS, SH_C0

    n = len(pts)
    q = np.stack([1.0 + nrm[:, 2], -nrm[:, 1], nrm[:, 0], np.zeros(n)], 1)
    flip = q[:, 0] < 1e-6                                   # the normal −z: a half turn about x
    q[flip] = [0.0, 1.0, 0.0, 0.0]
    q = 2.5 * q / np.linalg.norm(q, axis=1, keepdims=True)
    if zero_quat:
        q[3] = 0.0
    vals = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2],
            **{f"f_dc_{i}": (srgb[:, i] - 0.5) / SH_C0 for i in range(3)},
            "opacity": np.log(opacity / (1 - opacity)),
            "scale_0": np.log(sigma), "scale_1": np.log(sigma), "scale_2": np.log(sigma * 0.05),
            **{f"rot_{i}": q[:, i] for i in range(4)}}
    names = [k for k in GS_PROPS if k != drop] + [f"f_rest_{i}" for i in range(n_rest)]
    arr = np.zeros(n, dtype=[(k, "<f4") for k in names])
    for k in names:
        if k in vals:
            arr[k] = vals[k]
    if nan:
        arr[nan][5] = np.nan
    PlyData([PlyElement.describe(arr, "vertex")], byte_order="<").write(str(path))


def test_a_gaussian_splat_scene_imports_its_colours_normals_and_drops_what_it_says(tmp_path, sample, sample_u8):
    """Splats placed on the sample's points (every 10th), each with the point's 8-bit sRGB colour as its DC term,
    its normal as the shortest axis, σ = 1 cm; 500 transparent floaters (opacity 0.02) and 50 huge splats (σ 2 m)
    added: import keeps the colours within 1 % (8-bit sRGB through float32 f_dc) and the normals, and drops and
    counts the floaters and the huge ones; the report says what was dropped."""
    idx = np.arange(0, len(sample), 10)
    pts, nrm = sample.points[idx].astype(np.float64), sample.normals[idx].astype(np.float64)
    srgb = sample_u8[idx].astype(np.float64) / 255.0
    rng = np.random.default_rng(4)
    n, fl, big = len(idx), 500, 50
    lo, hi = pts.min(0), pts.max(0)
    P = np.concatenate([pts, rng.uniform(lo, hi, (fl + big, 3))])
    d = rng.normal(size=(fl + big, 3))
    N = np.concatenate([nrm, d / np.linalg.norm(d, axis=1, keepdims=True)])
    C = np.concatenate([srgb, rng.uniform(0, 1, (fl + big, 3))])
    sig = np.concatenate([np.full(n, 0.01), np.full(fl, 0.01), np.full(big, 2.0)])
    op = np.concatenate([np.full(n, 0.95), np.full(fl, 0.02), np.full(big, 0.9)])
    _write_splats(tmp_path / "room_splats.ply", P, N, C, sig, op)
    code, err, out, rep = _import(tmp_path, tmp_path / "room_splats.ply", "--units", "m", "--up", "y")
    assert code == 0, err
    got = io.read_cloud(out)
    text = json.dumps(rep)
    assert "Gaussian splats" in text and '"dropped_transparent": 500' in text and '"dropped_large": 50' in text, text
    assert len(got) <= n and len(got) >= 0.98 * n          # (import's own outlier removal may take a few)
    from scipy.spatial import cKDTree

    dist, j = cKDTree(pts).query(got.points.astype(np.float64))
    assert dist.max() < 1e-4
    want = sample.colors[idx][j].astype(np.float64)
    rel = np.abs(got.colors - want) / np.maximum(want, 1e-3)
    assert np.percentile(rel[want > 0.02], 99) <= 0.01, np.percentile(rel, 99)
    assert float(np.abs(np.sum(got.normals * nrm[j], axis=1)).min()) > 0.999


@pytest.mark.parametrize("case", ["missing", "nan", "zero_quat"])
def test_a_bad_splat_file_is_one_line_exit_1(tmp_path, sample, case):
    pts = sample.points[:200].astype(np.float64)
    nrm = sample.normals[:200].astype(np.float64)
    kw = {"missing": {"drop": "rot_3"}, "nan": {"nan": "f_dc_1"}, "zero_quat": {"zero_quat": True}}[case]
    _write_splats(tmp_path / "bad.ply", pts, nrm, np.full((200, 3), 0.5), np.full(200, 0.01), np.full(200, 0.9), **kw)
    code, err, out, _ = _import(tmp_path, tmp_path / "bad.ply")
    lines = [ln for ln in err.strip().splitlines() if ln]
    assert code == 1 and len(lines) == 1 and lines[0].startswith(f"pcrelight: {tmp_path / 'bad.ply'}: "), err
    assert {"missing": "without rot_3", "nan": "non-finite 'f_dc_1'", "zero_quat": "zero rotation quaternion"}[case] in err
    assert not out.exists()


def test_write_gaussian_splats_is_the_readers_inverse(tmp_path):
    """io.write_gaussian_splats → read_gaussian_splats: centres and linear colours back to float32 precision, each
    normal the splat's shortest axis, every splat kept (opacity 0.9, small)."""
    from pipeline.camera import quat_matrix
    from pipeline.color import srgb_decode

    rng = np.random.default_rng(4)
    n = 500
    pos = rng.uniform(-2, 2, (n, 3))
    sigma = np.stack([np.full(n, 0.03), np.full(n, 0.02), np.full(n, 0.001)], 1)
    quat = rng.normal(size=(n, 4))
    srgb = rng.uniform(0.05, 0.95, (n, 3))
    io.write_gaussian_splats(tmp_path / "s.ply", pos, sigma, quat, np.full(n, 0.9), srgb)
    scan = io.read_gaussian_splats(tmp_path / "s.ply")
    assert len(scan.points) == n and scan.info["dropped_transparent"] == scan.info["dropped_large"] == 0
    np.testing.assert_allclose(scan.points, pos, atol=1e-6)
    np.testing.assert_allclose(scan.colors, srgb_decode(srgb), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(np.abs(np.sum(scan.normals * quat_matrix(quat)[:, :, 2], 1)), 1.0, atol=1e-5)
