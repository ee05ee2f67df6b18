"""Cameras: the one home of every camera the pipeline uses, and the table of camera models.

Conventions (world: right-handed, +Y up, metres; angles in degrees where the name says ``_deg``, else radians)
---------------------------------------------------------------------------------------------------------
* **Photo cameras** (make-scene's views and photos, the registered photo of exposure.npz, scene.json's views):
  OpenCV axes — x right, y down, z forward; ``world_to_camera`` = [R | −R·eye] (4×4); pinhole intrinsics
  ``K`` (3×3, pixels) with pixel (0, 0)'s corner at (0, 0) and pixel centres at i + 0.5; the field of view is
  vertical (:func:`intrinsics`). :func:`look_at`, :func:`look_rotation`, :func:`camera_rays`.
* **Cube-map faces** (cameras.npz, :func:`cube_cameras`): OpenGL camera axes — x right, y up, looking down −z —
  rotated as OpenGL renders cube-map faces (:data:`FACE_NAMES`, :func:`face_rotations`); the pixel rule is
  :mod:`pipeline.expansion.splats`' (rows in file order = GL's bottom-up rows).
* **relight's view camera** (:class:`Camera`): eye, target, up, vertical field of view, size; OpenGL view and
  projection matrices for the G-buffer and its pixel-centre rays.

Camera models (:data:`MODELS`: ``pinhole``, ``equirect``, ``fisheye``), each two functions on OpenCV camera
axes: ``directions(size, params)`` → (H, W, 3) unit directions through the pixel centres (row 0 at the top of the
image), and ``project(dirs, size, params)`` → (u, v, ok): continuous pixel coordinates (column, row; a pixel's
centre at i + 0.5) of unit directions (N, 3) and whether the model sees them. ``params``: ``K`` (pinhole);
``fov_deg`` (fisheye: the circle's full field of view, equidistant r = f·θ, f = min(W, H)/2 ÷ (fov/2));
nothing (equirect: the full sphere; column 0 at longitude −π, the centre column along +z, row 0 at the zenith
−y).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

# world→camera rotation of a panorama placed at a known centre, yaw 0 (OpenCV axes: the centre column along world +Z)
PANORAMA_ROTATION = np.array([[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]])



def quat_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) of quaternions (N, 4) as (w, x, y, z), normalised here (a 3D Gaussian splat's
    ``rot_0…3``): the matrix maps the splat's own axes to world axes (its columns are those axes)."""
    q = np.asarray(q, np.float64).reshape(-1, 4)
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)


# ----------------------------------------------------------------------------- photo cameras (OpenCV axes)
def look_at(eye, target, up) -> np.ndarray:
    """World→camera 4×4 (OpenCV: x right, y down, z forward)."""
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    f = target - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)                     # camera up (world)
    R = np.stack([r, -u, f])               # rows: camera x, y (down), z axes in world coordinates
    return pose_matrix(R, eye)


def pose_matrix(R: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """World→camera 4×4 [R | −R·eye] of the rotation ``R`` (rows: the camera's axes in world coordinates) and the
    camera centre ``eye`` [m]."""
    R = np.asarray(R, dtype=np.float64)
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = -R @ np.asarray(eye, dtype=np.float64)
    return M


def intrinsics(fov_deg: float, size) -> np.ndarray:
    """Pinhole OpenCV K (3,3) [pixels] for a vertical field of view [degrees] and ``size`` (width, height)
    [pixels], principal point at the image centre."""
    w, h = size
    f = (h / 2.0) / np.tan(np.radians(fov_deg) / 2.0)
    return np.array([[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]])


def look_rotation(forward: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """World→camera rotation (3,3), OpenCV axes, looking along ``forward`` (unit), image up as close
    to world +Y as possible, then rolled by ``roll`` [rad] about the view axis."""
    f = np.asarray(forward, float) / np.linalg.norm(forward)
    up = np.array([0.0, 1.0, 0.0]) if abs(f[1]) < 0.999 else np.array([0.0, 0.0, 1.0])
    x, y, z = look_at(np.zeros(3), f, up)[:3, :3]
    c, s = np.cos(roll), np.sin(roll)
    return np.stack([c * x + s * y, -s * x + c * y, z])


def camera_rays(world_to_camera: np.ndarray, K: np.ndarray, size, jitter: np.ndarray | None = None):
    """Pinhole rays: (origins (H·W,3), unit world directions (H·W,3)) row-major from the top row; ``jitter``
    (H·W,2) in [0,1)² replaces the pixel-centre offsets 0.5."""
    w, h = size
    j, i = np.mgrid[0:h, 0:w]
    off = np.full((h * w, 2), 0.5) if jitter is None else jitter
    u = i.reshape(-1) + off[:, 0]
    v = j.reshape(-1) + off[:, 1]
    dc = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=1)
    R = world_to_camera[:3, :3]
    eye = -R.T @ world_to_camera[:3, 3]
    d = dc @ R                              # R^T · dc for every row
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.repeat(eye[None], len(d), axis=0), d


# ----------------------------------------------------------------------------- camera models (OpenCV axes)
def _pixel_centres(size) -> tuple[np.ndarray, np.ndarray]:
    w, h = size
    return np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)


def _unit(d: np.ndarray) -> np.ndarray:
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def pinhole_directions(size, K: np.ndarray) -> np.ndarray:
    """(H, W, 3) unit camera-space directions of a pinhole camera with intrinsics ``K``."""
    u, v = _pixel_centres(size)
    return _unit(np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1))


def pinhole_project(dirs: np.ndarray, size, K: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, v, ok) of camera-space directions (N, 3): in front (z > 0) and inside the image."""
    d = np.asarray(dirs, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * d[:, 0] / d[:, 2] + K[0, 2]
        v = K[1, 1] * d[:, 1] / d[:, 2] + K[1, 2]
    ok = (d[:, 2] > 0) & (u >= 0) & (u < size[0]) & (v >= 0) & (v < size[1])
    return u, v, ok


def equirect_directions(size) -> np.ndarray:
    """(H, W, 3) unit directions of an equirectangular (latitude-longitude) image: longitude
    φ = 2π·u/W − π about −y (φ = 0: +z, φ = π/2: +x), latitude θ = π/2 − π·v/H (row 0: the zenith −y)."""
    w, h = size
    u, v = _pixel_centres(size)
    lon, lat = 2.0 * np.pi * u / w - np.pi, np.pi / 2.0 - np.pi * v / h
    return np.stack([np.cos(lat) * np.sin(lon), -np.sin(lat), np.cos(lat) * np.cos(lon)], axis=-1)


def equirect_project(dirs: np.ndarray, size) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, v, ok) of unit camera-space directions (N, 3) in an equirectangular image (every one is seen)."""
    d = np.asarray(dirs, np.float64)
    w, h = size
    lon = np.arctan2(d[:, 0], d[:, 2])
    lat = np.arcsin(np.clip(-d[:, 1], -1.0, 1.0))
    u = np.mod((lon + np.pi) / (2.0 * np.pi) * w, w)
    v = (np.pi / 2.0 - lat) / np.pi * h
    return u, v, np.isfinite(u) & np.isfinite(v)


def _fisheye_f(size, fov_deg: float) -> float:
    return min(size) / 2.0 / (np.radians(fov_deg) / 2.0)


def fisheye_directions(size, fov_deg: float) -> np.ndarray:
    """(H, W, 3) unit directions of an equidistant fisheye (r = f·θ from the image centre, the circle of
    diameter min(W, H) spanning ``fov_deg``); pixels outside the circle get directions beyond fov/2 (θ up to π),
    which :func:`fisheye_project` reports as not seen."""
    w, h = size
    u, v = _pixel_centres(size)
    x, y = u - w / 2.0, v - h / 2.0
    r = np.hypot(x, y)
    theta = np.minimum(r / _fisheye_f(size, fov_deg), np.pi)
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.where(r > 0, np.sin(theta) / r, 0.0)
    return np.stack([x * s, y * s, np.cos(theta)], axis=-1)


def fisheye_project(dirs: np.ndarray, size, fov_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, v, ok) of unit camera-space directions (N, 3) in an equidistant fisheye: seen within fov/2 of +z."""
    d = np.asarray(dirs, np.float64)
    w, h = size
    theta = np.arccos(np.clip(d[:, 2], -1.0, 1.0))
    rxy = np.hypot(d[:, 0], d[:, 1])
    f = _fisheye_f(size, fov_deg)
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.where(rxy > 0, f * theta / rxy, 0.0)
    u, v = w / 2.0 + d[:, 0] * s, h / 2.0 + d[:, 1] * s
    ok = (theta <= np.radians(fov_deg) / 2.0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    return u, v, ok


@dataclass(frozen=True)
class Model:
    """A camera model: ``directions(size, **params)`` and ``project(dirs, size, **params)`` (camera space,
    OpenCV axes) and the names of its parameters."""

    directions: Callable[..., np.ndarray]
    project: Callable[..., tuple[np.ndarray, np.ndarray, np.ndarray]]
    params: tuple[str, ...]


MODELS: dict[str, Model] = {
    "pinhole": Model(pinhole_directions, pinhole_project, ("K",)),
    "equirect": Model(equirect_directions, equirect_project, ()),
    "fisheye": Model(fisheye_directions, fisheye_project, ("fov_deg",)),
}


def world_rays(model: str, size, world_to_camera: np.ndarray, **params: Any) -> tuple[np.ndarray, np.ndarray]:
    """(eye (3,), unit world directions (H, W, 3)) of a camera of model ``model`` at ``world_to_camera``."""
    R = np.asarray(world_to_camera, np.float64)[:3, :3]
    eye = -R.T @ np.asarray(world_to_camera, np.float64)[:3, 3]
    return eye, MODELS[model].directions(size, **params) @ R


def project_points(model: str, points: np.ndarray, size, world_to_camera: np.ndarray,
                   **params: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(u, v, distance [m], ok) of world points (N, 3) in a camera of model ``model``."""
    M = np.asarray(world_to_camera, np.float64)
    c = np.asarray(points, np.float64) @ M[:3, :3].T + M[:3, 3]
    dist = np.linalg.norm(c, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        u, v, ok = MODELS[model].project(c / dist[:, None], size, **params)
    return u, v, dist, ok & (dist > 0)


# ----------------------------------------------------------------------------- cube-map faces (OpenGL axes)
FACE_NAMES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")
# (forward, up) per face: the OpenGL cube-map rendering table.
_FACE_DIRS = (
    ((1, 0, 0), (0, -1, 0)),
    ((-1, 0, 0), (0, -1, 0)),
    ((0, 1, 0), (0, 0, 1)),
    ((0, -1, 0), (0, 0, -1)),
    ((0, 0, 1), (0, -1, 0)),
    ((0, 0, -1), (0, -1, 0)),
)


def face_rotations() -> np.ndarray:
    """(6,3,3) world→camera rotations (rows = camera x, y, z axes in world coordinates)."""
    out = np.zeros((6, 3, 3))
    for i, (fwd, up) in enumerate(_FACE_DIRS):
        f = np.asarray(fwd, float)
        u = np.asarray(up, float)
        z = -f
        x = np.cross(u, z)
        out[i] = np.stack([x, u, z])
    return out


def cube_cameras(eyes: np.ndarray, size: int) -> dict[str, np.ndarray]:
    """The arrays of ``cameras.npz`` (schema pcrelight.cameras/1) for cube maps at ``eyes`` (V,3)."""
    eyes = np.asarray(eyes, dtype=np.float64).reshape(-1, 3)
    v = len(eyes)
    rot = face_rotations()
    f = size / 2.0
    K = np.array([[f, 0.0, size / 2.0], [0.0, f, size / 2.0], [0.0, 0.0, 1.0]])
    w2c = np.zeros((v * 6, 4, 4))
    for vi in range(v):
        for fi in range(6):
            m = np.eye(4)
            m[:3, :3] = rot[fi]
            m[:3, 3] = -rot[fi] @ eyes[vi]
            w2c[vi * 6 + fi] = m
    return {
        "K": np.repeat(K[None], v * 6, axis=0),
        "world_to_camera": w2c,
        "resolution": np.full((v * 6, 2), size, dtype=np.int32),
        "view": np.repeat(np.arange(v, dtype=np.int32), 6),
        "face": np.tile(np.arange(6, dtype=np.int32), v),
        "eye": eyes,
    }


# ----------------------------------------------------------------------------- relight's view camera (OpenGL)
@dataclass
class Camera:
    """relight's view: a look-at pinhole camera (OpenGL view and projection matrices, pixel-centre rays)."""

    eye: np.ndarray      # (3,) metres
    target: np.ndarray   # (3,)
    up: np.ndarray       # (3,)
    fov_deg: float       # vertical
    size: tuple[int, int]  # (W, H)

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(right, true up, forward) unit vectors in world space."""
        f = np.asarray(self.target, np.float64) - np.asarray(self.eye, np.float64)
        f /= np.linalg.norm(f)
        r = np.cross(f, self.up)
        if np.linalg.norm(r) < 1e-12:  # up parallel to the view direction: pick another up
            r = np.cross(f, [1.0, 0.0, 0.0] if abs(f[0]) < 0.9 else [0.0, 0.0, 1.0])
        r /= np.linalg.norm(r)
        return r, np.cross(r, f), f

    def view_matrix(self) -> np.ndarray:
        """World → OpenGL eye space (camera looks down −z)."""
        r, u, f = self.basis()
        M = np.eye(4)
        M[0, :3], M[1, :3], M[2, :3] = r, u, -f
        M[:3, 3] = -M[:3, :3] @ np.asarray(self.eye, np.float64)
        return M

    def proj_matrix(self, near: float, far: float) -> np.ndarray:
        w, h = self.size
        t = 1.0 / np.tan(np.radians(self.fov_deg) / 2)
        P = np.zeros((4, 4))
        P[0, 0] = t * h / w
        P[1, 1] = t
        P[2, 2] = -(far + near) / (far - near)
        P[2, 3] = -2 * far * near / (far - near)
        P[3, 2] = -1.0
        return P

    def rays(self) -> np.ndarray:
        """Unit world directions through the pixel centres (H, W, 3), row 0 at the top."""
        w, h = self.size
        r, u, f = self.basis()
        t = np.tan(np.radians(self.fov_deg) / 2)
        x = ((np.arange(w) + 0.5) / w * 2 - 1) * t * w / h
        y = (1 - (np.arange(h) + 0.5) / h * 2) * t
        d = f[None, None] + x[None, :, None] * r[None, None] + y[:, None, None] * u[None, None]
        return d / np.linalg.norm(d, axis=-1, keepdims=True)


FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)   # what "35 mm equivalent" focal lengths refer to


def exif_fov(path: str | os.PathLike) -> tuple[float | None, dict[str, Any]]:
    """The photo's vertical field of view [degrees] from its EXIF (OpenImageIO): the 35 mm-equivalent focal
    length (``FocalLengthIn35mmFilm``, referred to the 43.3 mm diagonal), else the focal length with the
    focal-plane resolution (sensor size); None when the file carries neither."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        return None, {"by": "unreadable"}
    try:
        spec = inp.spec()
        w, h = int(spec.width), int(spec.height)
        attrs = {a.name: a.value for a in spec.extra_attribs}
    finally:
        inp.close()

    def num(name: str) -> float | None:
        v = attrs.get(name)
        try:
            v = float(v[0] / v[1]) if isinstance(v, tuple) and len(v) == 2 else float(v)
        except (TypeError, ValueError, ZeroDivisionError):
            return None
        return v if math.isfinite(v) and v > 0 else None

    f35 = num("Exif:FocalLengthIn35mmFilm")
    if f35:
        h_mm = FULL_FRAME_DIAGONAL_MM * h / math.hypot(w, h)
        fov = math.degrees(2 * math.atan(h_mm / (2 * f35)))
        return fov, {"by": f"EXIF FocalLengthIn35mmFilm {f35:g} mm (frame height {h_mm:.3g} mm of the 43.3 mm "
                           f"diagonal at {w}×{h})", "fov_deg": fov}
    f, xres = num("Exif:FocalLength"), num("Exif:FocalPlaneXResolution")
    unit = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}.get(int(num("Exif:FocalPlaneResolutionUnit") or 2), 25.4)
    if f and xres:
        full_w = num("Exif:PixelXDimension") or w
        sensor_w = full_w / xres * unit
        h_mm = sensor_w * h / w
        fov = math.degrees(2 * math.atan(h_mm / (2 * f)))
        return fov, {"by": f"EXIF FocalLength {f:g} mm and FocalPlaneXResolution {xres:g} (sensor {sensor_w:.3g} mm "
                           f"wide)", "fov_deg": fov}
    return None, {"by": "no focal length in the file's metadata"}


def parse_size(s: str) -> tuple[int, int]:
    """An image size 'WxH' [pixels] → (W, H) (one ConfigError line naming --size otherwise)."""
    from .errors import ConfigError

    try:
        w, h = (int(x) for x in s.lower().replace("×", "x").split("x"))
    except ValueError:
        raise ConfigError(f"--size must be WxH, got {s!r}") from None
    if not (1 <= w <= 16384 and 1 <= h <= 16384):
        raise ConfigError(f"--size must be within 1..16384 per side, got {s!r}")
    return w, h
