"""The bench library: helpers every bench script shares (scripts run as ``python -m bench.<topic>.<script>`` from
the repository root, so ``bench.benchlib`` and ``pipeline`` import without any ``sys.path`` edit).

No pipeline import at module level: the timing workers (speed/) import this module before they put another
checkout's ``pipeline`` first on ``sys.path``. Benches never import tests: the few test fixtures a bench needs have
their own copy at the end of this file.
"""

from __future__ import annotations

import csv
import math
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]   # the repository
BENCH = ROOT / "bench"
WORK = BENCH / "_work"                        # scratch (git-ignored)
RHO = 0.8                                     # part()'s albedo, as tests/test_surfels.py's


def module_cmd(spec_name: str, *args: str) -> list[str]:
    """The command that runs bench module ``spec_name`` (``__spec__.name``) again in a child process."""
    return [sys.executable, "-m", spec_name, *args]


# material_kw (from bench/relight/bench_relight_truth.py)
def material_kw(mat: str) -> dict:
    if mat == "lambert":
        return dict(brdf="lambert", albedo=(0.8, 0.8, 0.8))
    return dict(brdf="ggx", albedo=(1.0, 1.0, 1.0), metallic=1.0, roughness=float(mat[3:]), masking="separable")


# write_rows (from bench/relight/bench_relight_truth.py)
def write_rows(path: Path, rows: list[dict]) -> None:
    """The rows as a CSV (columns of the first row) at ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    print(f"wrote {path}")


# truth_bsh (from bench/relight/bench_relight_truth.py)
def truth_bsh(scene: Path, bsh: Path | None, work: Path) -> Path:
    """The BSH to relight with: ``bsh`` if given, else build-bsh (defaults) of the scene's cloud_gt.ply
    into ``work``."""
    work.mkdir(parents=True, exist_ok=True)
    if bsh is None:
        bsh = work / "bsh.npz"
        subprocess.run([sys.executable, str(ROOT / "cli.py"), "build-bsh", str(scene / "cloud_gt.ply"), "--out", str(bsh),
                        "-q"], check=True)
    return bsh


# material_args (from bench/peers/bench_vs_pathtracer.py)
def material_args(mat: str) -> list[str]:
    """relight's options for a scene.json reference material (as bench_relight_truth.material_kw)."""
    if mat == "lambert":
        return ["--brdf", "lambert", "--albedo", "0.8,0.8,0.8"]
    return ["--brdf", "ggx", "--albedo", "1,1,1", "--metallic", "1", "--roughness", mat[3:], "--masking", "separable"]


# measure (from bench/relight/bench_self_shadow.py; bench_relight_cases.py uses it too)
def measure(img: np.ndarray, scene: Path, view: str, mat: str, kind: str, k: int = 4) -> dict:
    """relight's image against the scene's ``truth/{kind}_{view}_{mat}`` trace on k×k block means: the mean ratio per
    channel and in all, the block relative RMS and the reference's own block noise (columns prefixed ``kind``)."""
    from pipeline import io
    from pipeline.metrics import compare_to_reference

    ref = io.read_image(scene / "truth" / f"{kind}_{view}_{mat}.exr")
    var = io.read_image(scene / "truth" / f"{kind}_{view}_{mat}_var.exr")
    sel = (img[..., 3] > 0.5) & (ref[..., 3] > 0.5)
    c = compare_to_reference(img, ref, sel, ref_var=var, block=k)
    r = c["mean_ratio_rgb_block"]
    return {f"{kind}_ratio_r": round(r[0], 4), f"{kind}_ratio_g": round(r[1], 4), f"{kind}_ratio_b": round(r[2], 4),
            f"{kind}_ratio": round(c["mean_ratio_block"], 4), f"{kind}_block_rms": round(c["rms_block"], 4),
            f"{kind}_block_noise": round(c["ref_noise_block"], 4)}


# load (from bench/speed/bench_walk_profile.py)
def load() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return ""


# synthetic_room (from bench/gatherers/bench_relight.py)
def synthetic_room(n: int = 20000, seed: int = 0):
    """Closed 6×3×6 m room (y up, floor at 0): coloured walls, grey floor/ceiling, a bright ceiling
    panel (radiance 50); inward normals. Returns points, normals, colours (float32) and two views."""
    rng = np.random.default_rng(seed)
    lo, hi = np.array([-3.0, 0.0, -3.0]), np.array([3.0, 3.0, 3.0])
    faces = [(0, -1, [0.8, 0.2, 0.2]), (0, 1, [0.2, 0.8, 0.2]), (1, -1, [0.6, 0.6, 0.6]),
             (1, 1, [0.7, 0.7, 0.7]), (2, -1, [0.2, 0.2, 0.8]), (2, 1, [0.8, 0.8, 0.3])]
    area = []
    for ax, _, _ in faces:
        o = [a for a in range(3) if a != ax]
        area.append((hi[o[0]] - lo[o[0]]) * (hi[o[1]] - lo[o[1]]))
    counts = np.floor(np.array(area) / sum(area) * n).astype(int)
    P, N, C = [], [], []
    for (ax, sgn, col), k in zip(faces, counts):
        p = lo + rng.random((k, 3)) * (hi - lo)
        p[:, ax] = lo[ax] if sgn < 0 else hi[ax]
        nrm = np.zeros((k, 3))
        nrm[:, ax] = 1.0 if sgn < 0 else -1.0
        c = np.tile(col, (k, 1)) * (0.6 + 0.8 * rng.random((k, 1)))    # scan-like texture noise
        if ax == 1 and sgn > 0:                       # ceiling light panel
            lit = (np.abs(p[:, 0]) < 1.0) & (np.abs(p[:, 2]) < 1.0)
            c[lit] = 50.0
        P.append(p), N.append(nrm), C.append(c)
    views = {"view1": {"eye": [0.0, 1.4, 1.0], "target": [0.0, 1.2, 0.0]},
             "view2": {"eye": [0.7, 1.9, -0.7], "target": [0.0, 1.2, 0.0]}}
    return (np.concatenate(P).astype(np.float32), np.concatenate(N).astype(np.float32),
            np.concatenate(C).astype(np.float32), views, np.array([0.0, 1.2, 0.0]), "synthetic-room")


# sphere_gbuffer (from bench/gatherers/bench_relight.py)
def sphere_gbuffer(size: int, eye, target, centre, radius: float = 0.35, fov: float = 45.0):
    """Ray-cast G-buffer of a sphere: (mask (H,W), position (P,3), normal (P,3), view (P,3), flat idx)."""
    eye, target, centre = (np.asarray(x, np.float64) for x in (eye, target, centre))
    f = target - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, [0.0, 1.0, 0.0])
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    t = np.tan(np.radians(fov) / 2)
    ys, xs = np.meshgrid((0.5 - (np.arange(size) + 0.5) / size) * 2 * t, ((np.arange(size) + 0.5) / size - 0.5) * 2 * t,
                         indexing="ij")
    d = xs[..., None] * r + ys[..., None] * u + f
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    oc = eye - centre
    b = d @ oc
    c = oc @ oc - radius ** 2
    disc = b * b - c
    mask = disc > 0
    tt = -b - np.sqrt(np.maximum(disc, 0))
    mask &= tt > 0
    pos = eye + tt[..., None] * d
    nrm = (pos - centre) / radius
    flat = np.flatnonzero(mask)
    P = pos.reshape(-1, 3)[flat].astype(np.float32)
    N = nrm.reshape(-1, 3)[flat]
    N = (N / np.linalg.norm(N, axis=1, keepdims=True)).astype(np.float32)
    V = (-d.reshape(-1, 3)[flat]).astype(np.float32)
    return mask, P, N, V, flat


# below: the bench's own copies of test fixtures (benches never import tests; tests keep theirs)
# plate_form_factor (as tests/test_gltf.py's: Howell B-3)
def plate_form_factor(a: float, b: float, c: float) -> float:
    """The differential form factor from a point to a parallel a × b rectangle at distance c above one of its
    corners (Howell's catalogue, B-3)."""
    A, B = a / c, b / c
    return (A / math.sqrt(1 + A * A) * math.atan(B / math.sqrt(1 + A * A))
            + B / math.sqrt(1 + B * B) * math.atan(A / math.sqrt(1 + B * B))) / (2 * math.pi)


# part (as tests/test_surfels.py's: a trimesh mesh as relight's object part, white Lambert RHO)
def part(mesh, normals=None) -> dict:
    import trimesh  # noqa: F401

    return {"positions": np.asarray(mesh.vertices, np.float32), "faces": np.asarray(mesh.faces, np.uint32),
            "normals": None if normals is None else np.asarray(normals, np.float32), "uv": None, "vertex_color": None,
            "base_color": np.full(3, RHO, np.float32), "metallic": 0.0, "roughness": 1.0, "base_color_tex": None,
            "mr_tex": None}
