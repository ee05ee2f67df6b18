"""The object in the photo (issue 44, pipeline/relight/composite.py): the registered camera, the room's receivers,
the differential shadow against an analytic case, the layers compositors read, and the refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline import camera, io
from pipeline.errors import InputError
from pipeline.relight import composite as cp


def _cam(eye=(0.0, 0.3, 3.0), target=(0.0, 0.0, 0.0), size=(64, 48), fov=50.0):
    return camera.Camera(np.asarray(eye, float), np.asarray(target, float), np.asarray([0.0, 1.0, 0.0]), fov, size)


def _opencv(cam):
    """(K, world_to_camera) of ``cam`` in OpenCV axes, as expose-match records a registered photo."""
    M = camera.look_at(np.asarray(cam.eye), np.asarray(cam.target), (0.0, 1.0, 0.0))
    return camera.intrinsics(cam.fov_deg, cam.size), M


def test_photo_camera_is_the_registered_pinhole():
    cam = _cam(eye=(1.0, 1.6, -2.0), target=(0.2, 1.0, 0.5), size=(96, 64), fov=63.0)
    K, M = _opencv(cam)
    got = cp.photo_camera(K, M, cam.size, "x.npz")
    assert got.fov_deg == pytest.approx(63.0, abs=1e-9) and got.size == (96, 64)
    assert np.allclose(got.view_matrix(), cam.view_matrix(), atol=1e-9)
    assert np.allclose(got.rays(), cam.rays(), atol=1e-9)          # the same pixel rays as the photo's camera


def test_photo_camera_refuses_what_relight_cannot_draw():
    cam = _cam()
    K, M = _opencv(cam)
    K2 = K.copy()
    K2[0, 2] += 3.0
    with pytest.raises(InputError, match="x.npz.*not a centred square-pixel pinhole"):
        cp.photo_camera(K2, M, cam.size, "x.npz")
    K3 = K.copy()
    K3[0, 0] *= 1.1
    with pytest.raises(InputError, match="not a centred"):
        cp.photo_camera(K3, M, cam.size, "x.npz")


def test_room_surface_lies_on_the_discs_plane_and_faces_the_camera():
    rng = np.random.default_rng(0)
    n = 20000
    p = np.stack([rng.uniform(-3, 3, n), np.zeros(n), rng.uniform(-3, 3, n)], 1)
    nrm = np.tile([0.0, -1.0, 0.0], (n, 1))                        # unoriented on purpose: the camera is above
    cam = _cam(eye=(0.0, 1.5, 3.0), target=(0.0, 0.0, 0.0))
    s = cp.room_surface(p, nrm, np.full(n, 0.06), cam)
    m = s["mask"]
    assert m.mean() > 0.5
    assert np.allclose(s["normal"][m], [0.0, 1.0, 0.0])
    assert np.all(np.abs(s["position"][m][:, 1] - cp.LIFT * 0.06) < 1e-5)   # on y = 0, lifted
    # the position is the pixel ray's hit: along the ray from the eye
    d = s["position"][m] - cam.eye
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    assert np.allclose(d, cam.rays()[m], atol=2e-3)


def _box_room(n: int = 36000, seed: int = 1):
    """The inside of a closed 8 × 4 × 8 m box (y ∈ [0, 4]) of radiance 1: points on its faces, normals inward."""
    rng = np.random.default_rng(seed)
    faces = [(1, 0.0, 1.0), (1, 4.0, -1.0), (0, -4.0, 1.0), (0, 4.0, -1.0), (2, -4.0, 1.0), (2, 4.0, -1.0)]
    area = np.array([64.0, 64.0, 32.0, 32.0, 32.0, 32.0])
    counts = np.round(n * area / area.sum()).astype(int)
    pts, nrm = [], []
    for (ax, c, s), k in zip(faces, counts):
        q = np.stack([rng.uniform(-4, 4, k), rng.uniform(0, 4, k), rng.uniform(-4, 4, k)], 1)
        q[:, ax] = c
        v = np.zeros((k, 3))
        v[:, ax] = s
        pts.append(q), nrm.append(v)
    p, v = np.concatenate(pts), np.concatenate(nrm)
    return p.astype(np.float32), v.astype(np.float32), np.ones((len(p), 3), np.float32)


@pytest.fixture(scope="module")
def sphere_over_floor(tmp_path_factory):
    """A black sphere (radius 0.5 m, centre 1 m above the floor) in the uniform box room, composited from a camera
    low over the floor into a flat photo (radiance 2 = the cloud's 1 ÷ α 0.5) registered by an exposure.npz."""
    import trimesh
    from click.testing import CliRunner

    import cli

    def cli_module(*args):
        r = CliRunner().invoke(cli.main, [str(a) for a in args], catch_exceptions=False)
        return r.exit_code, r.stdout, r.stderr

    d = tmp_path_factory.mktemp("composite")
    p, v, c = _box_room()
    io.write_cloud(d / "room.ply", io.Cloud(p, v, c))
    code, _, err = cli_module("build-bsh", d / "room.ply", "--out", d / "bsh.npz", "-q")
    assert code == 0, err
    m = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    m.apply_translation([0.0, 1.0, 0.0])
    io.write_mesh(d / "sphere.glb", m.vertices, m.faces, m.vertex_normals, base_color=(0.5, 0.5, 0.5))
    cam = _cam(eye=(0.0, 0.25, 1.2), size=(96, 72))                 # under the sphere's lower edge, over the floor
    K, M = _opencv(cam)
    W, H = cam.size
    io.write_image(d / "photo.exr", np.full((H, W, 3), 2.0, np.float32))
    io.write_npz(d / "exposure.npz", "pcrelight.exposure/1", alpha=0.5, log2_alpha=-1.0, distance=0.0,
                 tried_log2_alpha=np.zeros(1), tried_distance=np.zeros(1), tried_phase=np.zeros(1, np.int32),
                 cloud_hist=np.zeros(4), photo_hist=np.zeros(4), hist_space="srgb",
                 iterations=np.int32(0), photo_K=K, photo_world_to_camera=M)
    code, _, err = cli_module("relight", "--bsh", d / "bsh.npz", "--object", d / "sphere.glb", "--photo",
                              d / "photo.exr", "--exposure", d / "exposure.npz", "--albedo", "0,0,0",
                              "--microbuffer", "16", "--out", d / "out", "-q")
    assert code == 0, err
    return d, cam


def _layers(path):
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(path))
    px = buf.get_pixels(oiio.FLOAT)
    return {n: px[..., i] for i, n in enumerate(buf.spec().channelnames)}


def test_the_shadow_below_a_sphere_is_its_view_factor(sphere_over_floor):
    """A floor point straight below a sphere (radius R, centre at distance d) loses sin² = (R/d)² of its cosine-
    weighted hemisphere: in a room of uniform radiance with the sphere black, P'/P = 1 − (R/d)²."""
    d, cam = sphere_over_floor
    L = _layers(d / "out" / "composite.exr")
    rays = cam.rays()
    t = -cam.eye[1] / rays[..., 1]                                    # the floor y = 0 along each pixel ray
    hit = cam.eye + t[..., None] * rays
    r = np.hypot(hit[..., 0], hit[..., 2])
    floor = (rays[..., 1] < 0) & (L["A"] == 0)
    below = floor & (r < 0.15)
    assert below.sum() >= 4
    got = float(L["shadow.G"][below].mean())
    dist = np.sqrt(r[below] ** 2 + 1.0)                               # to the centre (0, 1, 0)
    want = float(np.mean(1 - (0.5 / dist) ** 2 * (1.0 / dist)))       # cos at the receiver: 1 / dist
    print(f"below the sphere: P'/P {got:.4f}, analytic {want:.4f}")
    assert got == pytest.approx(want, abs=0.03)


def test_receivers_are_where_the_object_may_change_the_light():
    """Room pixels are receivers where the bounding sphere may cover ≥ SHARE of the cosine-weighted hemisphere
    ((R/d)² ≥ SHARE) and is not wholly below their plane; the others keep the photo as it is."""
    x = np.linspace(0.0, 12.0, 25)
    pos = np.stack([x, np.zeros_like(x), np.zeros_like(x)], 1)[None].astype(np.float32)
    up = np.tile([0.0, 1.0, 0.0], (1, 25, 1)).astype(np.float32)
    surf = {"mask": np.ones((1, 25), bool), "position": pos, "normal": up}
    got = cp.near_pixels(surf, np.array([0.0, 1.0, 0.0]), 0.5)[0]
    d = np.hypot(x, 1.0)
    assert np.array_equal(got, (0.5 / d) ** 2 >= cp.SHARE)
    below = cp.near_pixels(surf, np.array([0.0, -1.0, 0.0]), 0.5)[0]   # wholly below every receiver's plane
    assert not below.any()


def test_composite_layers_are_what_a_compositor_reads(sphere_over_floor):
    d, cam = sphere_over_floor
    out = d / "out"
    L = _layers(out / "composite.exr")
    assert {"R", "G", "B", "A", "object.R", "object.A", "shadow.R", "depth.Z", "N.X"} <= set(L)
    a = L["A"]
    assert a.min() >= 0 and a.max() == 1 and ((a > 0) & (a < 1)).any()          # anti-aliased edges
    beauty = np.stack([L["R"], L["G"], L["B"]], -1)
    photo = io.read_image(d / "photo.exr")
    shadow = np.stack([L["shadow.R"], L["shadow.G"], L["shadow.B"]], -1)
    obj = np.stack([L["object.R"], L["object.G"], L["object.B"]], -1)
    # over: the premultiplied object plus the photo × the matte where the object does not cover
    assert np.allclose(beauty, obj + photo * shadow * (1 - a[..., None]), atol=1e-5)
    assert np.all(obj[a == 0] == 0) and np.all(shadow <= 1.0 + 1e-6)            # a black object only darkens
    stats = json.loads((out / "stats.json").read_text())["composite"]
    assert stats["background"] == "photo" and stats["receivers"] > 0 and stats["walked"] < stats["receivers"]
    assert (out / "composite.png").stat().st_size > 0
    assert np.all(L["depth.Z"][a > 0] > 0)


def test_photo_without_exposure_or_registration(sphere_over_floor, cli_run, tmp_path):
    d, _ = sphere_over_floor
    base = ("relight", "--bsh", d / "bsh.npz", "--object", d / "sphere.glb", "--eye", "0,0.3,3", "--target", "0,0,0",
            "--size", "32x24", "--microbuffer", "8")
    code, _, err = cli_run(*base, "--photo", d / "photo.exr", "--out", tmp_path / "a")
    assert code == 2 and "--photo needs --exposure" in err and len(err.strip().splitlines()) == 1
    ex = dict(np.load(d / "exposure.npz"))
    io.write_npz(tmp_path / "ex.npz", "pcrelight.exposure/1",
                 **{k: v for k, v in ex.items() if k not in ("schema", "photo_K", "photo_world_to_camera")})
    code, _, err = cli_run(*base, "--photo", d / "photo.exr", "--exposure", tmp_path / "ex.npz", "--out", tmp_path / "b")
    assert code == 0 and "no registered camera" in err
    st = json.loads((tmp_path / "b" / "stats.json").read_text())
    assert st["composite"]["background"].startswith("the room's BSH leaves") and st["camera"]["size"] == [32, 24]
    code, _, err = cli_run(*base, "--composite", "--surfels", "-1", "--out", tmp_path / "c")
    assert code == 2 and "needs the object in its own micro-buffers" in err


def test_an_own_room_run_composites_into_a_registered_photo(sphere_over_floor, tmp_path, caplog):
    """`run`'s relight renders from the photo's camera when exposure.npz registers it (relight gets --photo and
    --exposure), else keeps its automatic camera with one warning saying why."""
    import dataclasses

    from pipeline.io.workspace import Workspace
    from pipeline.run import runner
    from pipeline.run.stages import STAGE

    d, _ = sphere_over_floor
    ws = Workspace(tmp_path, tmp_path / "ws", cloud_file=d / "room.ply", photo_file=d / "photo.exr")
    ws.root.mkdir()
    (ws.root / "exposure.npz").write_bytes((d / "exposure.npz").read_bytes())
    assert runner._registered_photo(ws)
    st = STAGE["relight"]
    on = dataclasses.replace(ws, photo_view=True)
    paths = st.paths(None, on, None)
    assert paths["photo"] == ws.photo and paths["exposure"] == ws.exposure and ws.exposure in st.inputs(on)
    assert "photo" not in st.paths(None, ws, None)
    ex = dict(np.load(d / "exposure.npz"))
    io.write_npz(ws.exposure, "pcrelight.exposure/1",
                 **{k: v for k, v in ex.items() if k not in ("schema", "photo_K", "photo_world_to_camera")})
    with caplog.at_level("WARNING"):
        assert not runner._registered_photo(ws)
    assert "is not registered to the scan" in caplog.text
