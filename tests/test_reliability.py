"""Reliability sweep (issue 30): every bad input a new user might give answers one line
``pcrelight: <file>: <problem>`` with the documented exit status and writes nothing; a full disk and a
read-only output folder give a clear line and leave the previous output as it was; the same seed gives
byte-identical outputs. The catalogue of bad inputs below is what ``docs/errors.md`` is generated from
(this module rewrites it when a message changes, so the page cannot drift).

Exit statuses (README "Exit status"): 1 bad input (a data file or a value in one, a write that fails),
2 usage (a bad option on the command line or in a --config file) or a stage that is not built yet,
128 + N on signal N.
"""

from __future__ import annotations

import json
import os
import struct
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from pipeline import io

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "data_samples"
DOC = ROOT / "docs" / "errors.md"
ROWS: dict[str, tuple[str, str, int, str]] = {}   # case id → (what, command, exit status, stderr line)


# --------------------------------------------------------------------------------------------- inputs
def _cloud(path: Path, n: int = 1500, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    p = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
    nr = (-p / np.linalg.norm(p, axis=1, keepdims=True)).astype(np.float32)
    io.write_cloud(path, io.Cloud(p, nr, rng.uniform(0, 1, (n, 3)).astype(np.float32)))


def _glb(path: Path, **pbr) -> None:
    """A one-triangle GLB whose material's pbrMetallicRoughness gets ``pbr`` (written as given)."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    io.write_mesh(path.with_suffix(".tmpl.glb"), v, base_color=(0.5, 0.5, 0.5))
    b = path.with_suffix(".tmpl.glb").read_bytes()
    path.with_suffix(".tmpl.glb").unlink()
    clen = struct.unpack_from("<I", b, 12)[0]
    doc = json.loads(b[20:20 + clen])
    doc["materials"][0]["pbrMetallicRoughness"].update(pbr)
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    rest = b[20 + clen:]
    path.write_bytes(struct.pack("<III", 0x46546C67, 2, 20 + len(js) + len(rest)) + struct.pack("<II", len(js), 0x4E4F534A)
                     + js + rest)


def _scene(path: Path, edit) -> None:
    doc = json.loads((SAMPLES / "scene.json").read_text())
    edit(doc)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc))  # (Python writes NaN as NaN, which JSON readers accept)


def _ply_text(path: Path, rows: str, n: int | None = None) -> None:
    props = "".join(f"property float {x}\n" for x in "x y z nx ny nz red green blue".split())
    count = rows.count("\n") if n is None else n
    path.write_text(f"ply\nformat ascii 1.0\nelement vertex {count}\n{props}end_header\n{rows}")


def _with(img: np.ndarray, where: list[tuple[int, int, int]], value: float) -> np.ndarray:
    for y, x, c in where:
        img[y, x, c] = value
    return img


def _half_exr(path: Path, img: np.ndarray) -> None:
    """A half EXR as another tool writes it (OpenImageIO as is: 1e6 overflows to Inf; io.write_image refuses)."""
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(img.shape[1], img.shape[0], img.shape[2], "half"))
    out.write_image(img)
    out.close()


def _set(doc, keys, value):
    for k in keys[:-1]:
        doc = doc[k]
    doc[keys[-1]] = value


RELIGHT = ["relight", "--bsh", "b.npz", "--out", "relit", "-q"]
SCENE = ["--scene", "s/scene.json", "--view", "view1"]
CAM = ["--eye", "0,0,2", "--target", "0,0,0"]


@dataclass
class Case:
    id: str
    what: str
    argv: list[str]
    code: int
    needle: str
    files: dict = field(default_factory=dict)   # relative path → writer(Path)
    outputs: tuple[str, ...] = ("relit",)        # must hold no file afterwards


CASES = [
    # ---- config files (usage: exit 2, naming the file and the key or table)
    Case("toml-stray-key", "a config key above every table (it belongs to no stage)",
         ["build-bsh", "c.ply", "--out", "b.npz", "--config", "c.toml", "-q"], 2, "c.toml: key 'tc' belongs to no table",
         {"c.ply": _cloud, "c.toml": lambda p: p.write_text("tc = 0.5\n[build-bsh]\nbits = 16\n")}, ("b.npz",)),
    Case("toml-unknown-table", "a table that is no verb's ([build_bsh] for [build-bsh])",
         ["build-bsh", "c.ply", "--out", "b.npz", "--config", "c.toml", "-q"], 2, "c.toml: unknown table [build_bsh]",
         {"c.ply": _cloud, "c.toml": lambda p: p.write_text("[build_bsh]\ntc = 0.5\n")}, ("b.npz",)),
    Case("toml-unknown-key", "a misspelt key in a verb's table",
         ["build-bsh", "c.ply", "--out", "b.npz", "--config", "c.toml", "-q"], 2, "c.toml: unknown key 'tcc' in [build-bsh]",
         {"c.ply": _cloud, "c.toml": lambda p: p.write_text("[build-bsh]\ntcc = 0.5\n")}, ("b.npz",)),
    Case("toml-albedo", "an albedo above 1 in a config file (energy conservation)",
         RELIGHT + SCENE + ["--config", "c.toml"], 2, "c.toml: [relight] albedo must be in [0, 1]",
         {"c.toml": lambda p: p.write_text("[relight]\nalbedo = [0.5, 0.5, 2.0]\n")}),
    Case("toml-nan", "NaN in a config file",
         ["build-bsh", "c.ply", "--out", "b.npz", "--config", "c.toml", "-q"], 2, "c.toml: [build-bsh] tc must be finite",
         {"c.ply": _cloud, "c.toml": lambda p: p.write_text("[build-bsh]\ntc = nan\n")}, ("b.npz",)),
    Case("toml-type", "a string where a number belongs",
         ["build-bsh", "c.ply", "--out", "b.npz", "--config", "c.toml", "-q"], 2, "'bits' must be int",
         {"c.ply": _cloud, "c.toml": lambda p: p.write_text('[build-bsh]\nbits = "many"\n')}, ("b.npz",)),
    Case("toml-seed", "a negative top-level seed",
         ["build-bsh", "c.ply", "--out", "b.npz", "--config", "c.toml", "-q"], 2, "c.toml: seed (top level) must be",
         {"c.ply": _cloud, "c.toml": lambda p: p.write_text("seed = -1\n")}, ("b.npz",)),
    Case("toml-syntax", "a config file that is not TOML",
         ["build-bsh", "c.ply", "--out", "b.npz", "--config", "c.toml", "-q"], 1, "c.toml: not valid TOML",
         {"c.ply": _cloud, "c.toml": lambda p: p.write_text("[build-bsh\n")}, ("b.npz",)),
    # ---- options (usage: exit 2)
    Case("opt-albedo", "--albedo above 1", RELIGHT + SCENE + ["--albedo", "0.5,0.5,1.5"], 2, "--albedo must be in [0, 1]"),
    Case("opt-roughness", "--roughness above 1", RELIGHT + SCENE + ["--roughness", "1.5"], 2, "--roughness must be in [0, 1]"),
    Case("opt-metallic", "--metallic below 0", RELIGHT + SCENE + ["--metallic", "-0.1"], 2, "--metallic must be in [0, 1]"),
    Case("opt-fov", "--fov 180", RELIGHT + ["--eye", "0,0,2", "--target", "0,0,0", "--fov", "180"], 2, "--fov must be in (0, 180)"),
    Case("opt-up", "--up 0,0,0", RELIGHT + ["--eye", "0,0,2", "--target", "0,0,0", "--up", "0,0,0"], 2, "--up must be a non-zero vector"),
    Case("opt-nan", "--tc nan", ["build-bsh", "c.ply", "--out", "b.npz", "--tc", "nan", "-q"], 2, "--tc must be finite",
         {"c.ply": _cloud}, ("b.npz",)),
    Case("opt-inf", "--memory-budget inf", RELIGHT + SCENE + ["--memory-budget", "inf"], 2, "--memory-budget must be finite"),
    Case("opt-seed", "--seed -1", ["build-bsh", "c.ply", "--out", "b.npz", "--seed", "-1", "-q"], 2, "--seed must be",
         {"c.ply": _cloud}, ("b.npz",)),
    # ---- objects (bad input: exit 1)
    Case("gltf-basecolor", "a glTF base colour above 1", RELIGHT + CAM + ["--object", "o.glb"], 1,
         "o.glb: material 0: baseColorFactor [2.0, 0.5, 0.5, 1.0] must be 4 numbers in [0, 1]",
         {"o.glb": lambda p: _glb(p, baseColorFactor=[2.0, 0.5, 0.5, 1.0])}),
    Case("gltf-roughness", "a glTF roughness above 1", RELIGHT + CAM + ["--object", "o.glb"], 1,
         "o.glb: material 0: roughnessFactor 1.5 must be in [0, 1]", {"o.glb": lambda p: _glb(p, roughnessFactor=1.5)}),
    Case("gltf-metallic", "a negative glTF metallic", RELIGHT + CAM + ["--object", "o.glb"], 1,
         "o.glb: material 0: metallicFactor -1 must be in [0, 1]", {"o.glb": lambda p: _glb(p, metallicFactor=-1)}),
    Case("mtl-kd", "an OBJ whose MTL has Kd above 1", RELIGHT + CAM + ["--object", "o.obj"], 1,
         "o.mtl: line 2: material 'm': Kd (diffuse colour) 1.5 0.5 0.5 must be in [0, 1]",
         {"o.obj": lambda p: p.write_text("mtllib o.mtl\nusemtl m\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"),
          "o.mtl": lambda p: p.write_text("newmtl m\nKd 1.5 0.5 0.5\n")}),
    Case("obj-nan", "an OBJ vertex at NaN", RELIGHT + CAM + ["--object", "o.obj"], 1, "o.obj: non-finite vertex positions",
         {"o.obj": lambda p: p.write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")}),
    Case("object-missing", "an object file that does not exist", RELIGHT + CAM + ["--object", "nope.glb"], 1,
         "nope.glb: no such file"),
    # ---- scene.json (bad input: exit 1)
    Case("scene-fov", "a view's fov_deg of 0", RELIGHT + SCENE, 1, "scene.json: views.view1.fov_deg must be in (0, 180)",
         {"s/scene.json": lambda p: _scene(p, lambda d: _set(d, ["views", "view1", "fov_deg"], 0))}),
    Case("scene-size", "a view 0 pixels wide", RELIGHT + SCENE, 1, "scene.json: views.view1.size must be two integers",
         {"s/scene.json": lambda p: _scene(p, lambda d: _set(d, ["views", "view1", "size"], [0, 128]))}),
    Case("scene-eye", "eye = target", RELIGHT + SCENE, 1, "scene.json: views.view1: eye and target are the same point",
         {"s/scene.json": lambda p: _scene(p, lambda d: _set(d, ["views", "view1", "eye"], d["views"]["view1"]["target"]))}),
    Case("scene-nan", "NaN in a view's eye", RELIGHT + SCENE, 1, "scene.json: views.view1.eye[0] is nan",
         {"s/scene.json": lambda p: _scene(p, lambda d: _set(d, ["views", "view1", "eye"], [float("nan"), 1, 1]))}),
    Case("scene-to-world", "a singular object transform", RELIGHT + SCENE, 1, "scene.json: object.to_world is singular",
         {"s/scene.json": lambda p: _scene(p, lambda d: _set(d, ["object", "to_world"], [[0, 0, 0, 1], [0, 0, 0, 1], [0, 0, 0, 1], [0, 0, 0, 1]]))}),
    Case("scene-albedo", "a room mesh albedo above 1", RELIGHT + SCENE, 1, "scene.json: meshes[0].albedo must be in [0, 1]",
         {"s/scene.json": lambda p: _scene(p, lambda d: _set(d, ["meshes", 0, "albedo"], [1.2, 0.5, 0.5]))}),
    Case("scene-view-empty", "a view without a camera ({})", RELIGHT + SCENE, 1, "scene.json: views.view1 has no eye, target, up",
         {"s/scene.json": lambda p: _scene(p, lambda d: _set(d, ["views", "view1"], {}))}),
    Case("scene-view", "a view scene.json does not have", RELIGHT + ["--scene", "s/scene.json", "--view", "view9"], 1,
         "scene.json: no view 'view9'", {"s/scene.json": lambda p: _scene(p, lambda d: None)}),
    Case("scene-json", "a scene.json that is not JSON", RELIGHT + SCENE, 1, "scene.json: not valid JSON",
         {"s/scene.json": lambda p: (p.parent.mkdir(exist_ok=True), p.write_text("{\"views\": "))}),
    # ---- point clouds and stage files (bad input: exit 1)
    Case("ply-truncated", "a binary PLY cut short", ["build-bsh", "c.ply", "--out", "b.npz", "-q"], 1,
         "c.ply: not a readable PLY file", {"c.ply": lambda p: (_cloud(p), p.write_bytes(p.read_bytes()[:2000]))}, ("b.npz",)),
    Case("ply-count", "a PLY header that declares more points than it holds", ["build-bsh", "c.ply", "--out", "b.npz", "-q"], 1,
         "c.ply: not a readable PLY file (its header declares", {"c.ply": lambda p: _ply_text(p, "0 0 0 0 1 0 1 1 1\n", n=2 ** 31)},
         ("b.npz",)),
    Case("ply-nan", "a point with a NaN colour", ["build-bsh", "c.ply", "--out", "b.npz", "-q"], 1,
         "c.ply: 1 points have non-finite colors", {"c.ply": lambda p: _ply_text(p, "0 0 0 0 1 0 nan 1 1\n1 0 0 0 1 0 1 1 1\n")},
         ("b.npz",)),
    Case("ply-negative", "a negative colour", ["build-bsh", "c.ply", "--out", "b.npz", "-q"], 1,
         "c.ply: 1 points have negative colours", {"c.ply": lambda p: _ply_text(p, "0 0 0 0 1 0 -1 1 1\n1 0 0 0 1 0 1 1 1\n")},
         ("b.npz",)),
    Case("ply-missing", "an input that does not exist", ["build-bsh", "nope.ply", "--out", "b.npz", "-q"], 1,
         "nope.ply: no such file", {}, ("b.npz",)),
    Case("npz-schema", "a stage file of the wrong kind (an exposure.npz given as the BSH)",
         ["relight", "--bsh", "e.npz", "--out", "relit", "-q", "--object", "o.glb", "--eye", "0,0,2", "--target", "0,0,0"], 1,
         "e.npz: schema is 'pcrelight.exposure/1', expected 'pcrelight.bsh/1'",
         {"o.glb": lambda p: _glb(p), "e.npz": lambda p: np.savez(p, schema=np.asarray("pcrelight.exposure/1"))}),
    Case("npz-pickle", "an NPZ holding Python objects (pickles are never read)",
         ["relight", "--bsh", "e.npz", "--out", "relit", "-q", "--object", "o.glb", "--eye", "0,0,2", "--target", "0,0,0"], 1,
         "e.npz: 'nodes' holds Python objects",
         {"o.glb": lambda p: _glb(p), "e.npz": lambda p: np.savez(p, schema=np.asarray("pcrelight.bsh/1"),
                                                                  nodes=np.array([{}], dtype=object))}),
    Case("exr-truncated", "a photo cut short", ["expose-match", "p.exr", "c.ply", "--out", "e.npz", "--photo-ldr", "l.exr", "-q"], 1,
         "p.exr: ", {"c.ply": _cloud, "p.exr": lambda p: (io.write_image(p, np.ones((16, 16, 3), np.float32)),
                                                         p.write_bytes(p.read_bytes()[:300]))}, ("e.npz", "l.exr")),
    Case("exr-nan", "a photo with NaN pixels", ["expose-match", "p.exr", "c.ply", "--out", "e.npz", "--photo-ldr", "l.exr", "-q"], 1,
         "p.exr: 2 of 16×16 pixels hold non-finite values (NaN; the first at x=3, y=2)",
         {"c.ply": _cloud, "p.exr": lambda p: io.write_image(p, _with(np.ones((16, 16, 3), np.float32), [(2, 3, 0), (9, 9, 1)], np.nan))},
         ("e.npz", "l.exr")),
    Case("exr-inf", "a half-float photo with an Inf pixel (a value above 65504 written as half by another tool)",
         ["expose-match", "p.exr", "c.ply", "--out", "e.npz", "--photo-ldr", "l.exr", "-q"], 1,
         "p.exr: 1 of 16×16 pixels hold non-finite values (Inf; the first at x=5, y=0)",
         {"c.ply": _cloud, "p.exr": lambda p: _half_exr(p, _with(np.ones((16, 16, 3), np.float32), [(0, 5, 2)], 1e6))},
         ("e.npz", "l.exr")),
]


@pytest.fixture
def in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _files_under(p: Path) -> list[Path]:
    if p.is_dir():
        return [f for f in p.rglob("*") if f.is_file()]
    return [p] if p.exists() else []


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_one_line_nothing_written(cli_run, in_tmp, case):
    for rel, writer in case.files.items():
        (in_tmp / rel).parent.mkdir(parents=True, exist_ok=True)
        writer(in_tmp / rel)
    before = {f for f in in_tmp.rglob("*") if f.is_file()}
    code, out, err = cli_run(*case.argv)
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("pcrelight: "), err
    assert case.needle in lines[0], (case.needle, lines[0])
    assert code == case.code, (code, lines[0])
    assert "Traceback" not in err and "internal error" not in err
    for o in case.outputs:
        assert not _files_under(in_tmp / o), f"{o} written despite the error"
    assert {f for f in in_tmp.rglob("*") if f.is_file()} == before, "a file was written"
    ROWS[case.id] = (case.what, "pcrelight " + " ".join(a for a in case.argv if a != "-q"), code, lines[0])


def test_missing_camera_is_bad_input(cli_run, in_tmp):
    _glb(in_tmp / "o.glb")
    code, out, err = cli_run("relight", "--bsh", "b.npz", "--object", "o.glb", "--out", "relit", "-q")
    ROWS["relight-no-camera"] = ("relight without --scene or --eye (no camera)", "pcrelight relight --bsh b.npz --object o.glb "
                                 "--out relit", code, err.strip())
    assert err.count("\n") == 1 and "needs a camera" in err
    assert code == 1


# --------------------------------------------------------------------------------------------- disks
def _mount_tmpfs(where: Path, size: str, ro: bool = False) -> None:
    where.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({r.stderr.strip() or r.returncode})")


def _umount(where: Path) -> None:
    subprocess.run(["umount", "-l", str(where)], capture_output=True)


def _bsh_then_fill(cli_run, in_tmp: Path, out: Path) -> dict[str, bytes]:
    """build-bsh once into ``out`` (the previous output), return its files' bytes."""
    code, _, err = cli_run("build-bsh", "c.ply", "--out", str(out / "b.npz"), "--preview", str(out / "b.png"), "-q")
    assert code == 0, err
    return {f.name: f.read_bytes() for f in out.iterdir()}


@pytest.mark.skipif(os.geteuid() != 0, reason="mounting a small tmpfs needs root")
def test_disk_full_clear_error_previous_output_intact(cli_run, in_tmp):
    _cloud(in_tmp / "c.ply")
    out = in_tmp / "full"
    _mount_tmpfs(out, "4m")
    try:
        prev = _bsh_then_fill(cli_run, in_tmp, out)
        used = sum(len(b) for b in prev.values())
        size_k = (used + len(prev["b.npz"]) // 2) // 1024 + 8  # room for half a second BSH
        r = subprocess.run(["mount", "-o", f"remount,size={size_k}k", str(out)], capture_output=True, text=True)
        if r.returncode != 0:
            pytest.skip(f"cannot shrink the tmpfs ({r.stderr.strip()})")
        free = os.statvfs(out).f_bavail * os.statvfs(out).f_frsize
        assert free < len(prev["b.npz"]), "the tmpfs must be too small for a second BSH"
        code, _, err = cli_run("build-bsh", "c.ply", "--out", str(out / "b.npz"), "--tc", "0.02", "--preview",
                               str(out / "b.png"), "-q")
        line = err.strip().replace(str(in_tmp) + "/", "")
        assert code == 1 and err.count("\n") == 1, err
        assert line.startswith("pcrelight: full/b.npz: cannot write (no space left on device)"), line
        assert {f.name: f.read_bytes() for f in out.iterdir()} == prev  # nothing half-written, no temp file
        ROWS["disk-full"] = ("the output's disk is full (a tmpfs with room for half the file)", "pcrelight build-bsh c.ply --out full/b.npz", code, line)
    finally:
        _umount(out)


def test_read_only_output_folder(cli_run, in_tmp):
    _cloud(in_tmp / "c.ply")
    out = in_tmp / "ro"
    root = os.geteuid() == 0
    if root:  # root ignores permission bits: a read-only mount
        _mount_tmpfs(out, "4m")
    else:
        out.mkdir()
    try:
        prev = _bsh_then_fill(cli_run, in_tmp, out)
        if root:
            r = subprocess.run(["mount", "-o", "remount,ro", str(out)], capture_output=True, text=True)
            if r.returncode != 0:
                pytest.skip(f"cannot remount read-only ({r.stderr.strip()})")
        else:
            out.chmod(0o555)
        code, _, err = cli_run("build-bsh", "c.ply", "--out", str(out / "b.npz"), "--tc", "0.02", "-q")
        line = err.strip().replace(str(in_tmp) + "/", "")
        assert code == 1 and err.count("\n") == 1, err
        assert line.startswith("pcrelight: ro/b.npz: cannot write (read-only file system)" if root else
                               "pcrelight: ro/b.npz: cannot write (permission denied)"), line
        assert {f.name: f.read_bytes() for f in out.iterdir()} == prev
        ROWS["read-only"] = ("the output folder is read-only", "pcrelight build-bsh c.ply --out ro/b.npz", code, line)
        _glb(in_tmp / "o.glb")                   # valid inputs: relight reads them before it makes its output folder
        code, _, err = cli_run("relight", "--bsh", str(out / "b.npz"), "--object", "o.glb", "--eye", "0,0,2", "--target",
                               "0,0,0", "--out", str(out / "relit"), "-q")
        assert code == 1 and err.count("\n") == 1, err
        assert ("read-only file system" if root else "permission denied") in err.lower(), err
    finally:
        if root:
            _umount(out)
        else:
            out.chmod(0o755)


# --------------------------------------------------------------------------------------------- determinism
def _strip_timings(o):
    """A report without its clock readings (keys naming a time: timings, seconds, *_s) and without what the run's
    history decides (*_cache: whether relight read the object, its BSH and its lit state from the cache folder — a
    second run reads what the first wrote; the bytes are the same, tests/test_surfels.py)."""
    if isinstance(o, dict):
        return {k: _strip_timings(v) for k, v in o.items()
                if not ("timing" in k or "seconds" in k or k.endswith("_s") or k.endswith("_cache")
                        or k in ("elapsed", "time"))}
    if isinstance(o, list):
        return [_strip_timings(v) for v in o]
    return o


def _snapshot(folder: Path) -> dict[str, object]:
    snap: dict[str, object] = {}
    for f in sorted(folder.rglob("*")):
        if f.is_file():
            rel = str(f.relative_to(folder))
            snap[rel] = _strip_timings(json.loads(f.read_text())) if f.suffix == ".json" else f.read_bytes()
    return snap


def _box_room(path: Path, n: int = 3000) -> None:
    """An LDR cloud on the walls of a 4 × 3 × 4 m box with a saturated patch (something to expand)."""
    rng = np.random.default_rng(0)
    face, uv = rng.integers(0, 6, n), rng.uniform(-1, 1, (n, 2))
    p, nr = np.zeros((n, 3)), np.zeros((n, 3))
    for f in range(6):
        m, ax, sgn = face == f, f // 2, 1 if f % 2 else -1
        o = [a for a in range(3) if a != ax]
        p[m, ax], p[m, o[0]], p[m, o[1]], nr[m, ax] = sgn, uv[m, 0], uv[m, 1], -sgn
    c = rng.uniform(0.1, 0.6, (n, 3))
    c[(face == 3) & (np.abs(uv[:, 0]) < 0.4)] = 1.0
    io.write_cloud(path, io.Cloud((p * [2, 1.5, 2]).astype(np.float32), nr.astype(np.float32), c.astype(np.float32)),
                   uchar_colors=True)


def _scaled(c: io.Cloud, s: float) -> io.Cloud:
    c.colors = (c.colors * np.float32(s)).astype(np.float32)
    return c


def test_same_seed_byte_identical_every_stage(cli_run, in_tmp):
    """The pipeline's stages (expose-match … relight, on a small box room; evaluate on the shipped sample)
    twice with the same seed: every output file byte-identical, the JSON reports equal but for their clock
    readings. (make-scene: test_scene; across processes: test_kill's reference runs.)"""
    _box_room(in_tmp / "ldr.ply")
    io.write_image(in_tmp / "photo.exr", np.random.default_rng(1).uniform(0, 6, (24, 32, 3)).astype(np.float32))
    io.write_mesh(in_tmp / "o.glb", np.array([[0, 0, 0], [0.5, 0, 0], [0, 0.5, 0], [0, 0, 0.5]], np.float32),
                  np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]]))
    cmds = [["expose-match", "photo.exr", "ldr.ply", "--out", "o/e.npz", "--photo-ldr", "o/pl.exr", "--preview", "o/e.png",
             "--alpha-from", "histogram"],
            ["render-cubemaps", "ldr.ply", "--out", "o/cm", "--size", "32", "--probe-size", "16", "--preview", "o/cm.png"],
            ["patchmatch", "o/cm", "--photo", "photo.exr", "--photo-ldr", "o/pl.exr", "--exposure", "o/e.npz", "--out", "o/hf",
             "--iterations", "2", "--levels", "1", "--preview", "o/hf.png"],
            ["reproject", "ldr.ply", "o/cm", "o/hf", "--out", "o/proj.ply", "--photo", "photo.exr", "--exposure", "o/e.npz",
             "--preview", "o/proj.png"],
            ["poisson", "o/proj.ply", "--ldr", "ldr.ply", "--out", "o/hdr.ply", "--preview", "o/hdr.png"],
            ["build-bsh", "o/hdr.ply", "--out", "o/b.npz", "--preview", "o/b.png"],
            ["relight", "--bsh", "o/b.npz", "--object", "o.glb", "--eye", "0,0.2,1.5", "--target", "0,0.1,0", "--size", "16x12",
             "--microbuffer", "8", "--out", "o/relit"],
            # (the rendering columns are build-bsh + relight, above; the shipped sample as the truth)
            ["evaluate", "--truth", str(SAMPLES), str(SAMPLES / "cloud_ldr.ply"), "o/hdr_sample.ply", "--no-render", "--json",
             "o/t.json", "--md", "o/t.md", "--preview", "o/t.png"]]
    io.write_cloud(in_tmp / "o" / "hdr_sample.ply", _scaled(io.read_cloud(SAMPLES / "cloud_ldr.ply"), 1.5))
    snaps = []
    for run in range(2):  # the same paths twice (the reports name them)
        for c in cmds:
            code, _, err = cli_run(*c, "--seed", "5", "-q")
            assert code == 0, (c, err)
        snaps.append(_snapshot(in_tmp / "o"))
    assert sorted(snaps[0]) == sorted(snaps[1]) and len(snaps[0]) >= 30, sorted(snaps[0])
    for k in snaps[0]:
        assert snaps[0][k] == snaps[1][k], f"{k} differs between two runs with the same seed"


# --------------------------------------------------------------------------------------------- the page
def test_zz_errors_page_is_generated():
    """docs/errors.md is what the cases above print (runs last in this module): the committed page is checked, and
    rewritten only on request (``PCRELIGHT_WRITE_DOCS=1 pytest tests/test_reliability.py``)."""
    if not all(c.id in ROWS for c in CASES):
        pytest.skip("run the whole module to regenerate docs/errors.md")
    order = [c.id for c in CASES] + [k for k in ("relight-no-camera", "disk-full", "read-only") if k in ROWS]
    lines = ["# What pcrelight answers to bad input",
             "",
             "Generated by `tests/test_reliability.py` from the bad inputs it tries (do not edit by hand: run",
             "`pytest tests/test_reliability.py` and commit the result). Every case prints exactly this one line on",
             "stderr, exits with the status shown and writes no file. Exit status: 1 bad input (a data file, a",
             "value in one, an output that cannot be written), 2 usage (a bad option on the command line or in a",
             "`--config` file) or a stage not built yet, 128 + N on signal N (SIGINT 130, SIGTERM 143; outputs left",
             "as they were, temp files removed).",
             "",
             "| what the user gave | command | exit | what they see |",
             "|---|---|---|---|"]
    for k in order:
        what, cmd, code, line = ROWS[k]
        esc = lambda s: s.replace("|", "\\|")  # noqa: E731
        lines.append(f"| {esc(what)} | `{esc(cmd)}` | {code} | `{esc(line)}` |")
    text = "\n".join(lines) + "\n"
    if os.environ.get("PCRELIGHT_WRITE_DOCS") == "1" and (not DOC.exists() or DOC.read_text() != text):
        DOC.parent.mkdir(exist_ok=True)
        DOC.write_text(text)
    assert len(order) >= 30
    assert DOC.exists() and DOC.read_text() == text, \
        "docs/errors.md is not what pcrelight prints: PCRELIGHT_WRITE_DOCS=1 pytest tests/test_reliability.py"
