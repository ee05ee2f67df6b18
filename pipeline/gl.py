"""The only place that creates OpenGL contexts, plus helpers to load ``.glsl`` files.

Headless route: ``moderngl.create_context(standalone=True, backend="egl", require=430)`` — on
machines without a GPU this is Mesa's llvmpipe (CPU), on a lent GPU the vendor's driver.
Fallback (measured to work here: same llvmpipe, GL 4.5 core, draw + GS/TF smoke test pass):
glcontext 3.1 (moderngl's context library) has no OSMesa backend, so pcrelight makes an OSMesa
core-profile context current through PyOpenGL (``pip install 'pcrelight[osmesa]'``, apt
``libosmesa6``) and hands moderngl a loader built on ``OSMesaGetProcAddress``. The error says what
to install when neither works. ``PCRELIGHT_GL_BACKEND=egl|osmesa`` forces one route.
``PCRELIGHT_EGL_DEVICE=N`` picks the N-th EGL device (EGL device enumeration, ``eglQueryDevicesEXT``; default 0):
on a node with several GPUs each worker of ``pcrelight batch`` takes its own (:mod:`pipeline.run.batch`).

Pitfall (measured): with a standalone EGL context nothing is written by a draw call — or by
transform feedback — unless a framebuffer is bound first (``fbo.use()``); only ``ctx.error``
tells. :func:`bind_dummy_framebuffer` does that for shaders that write no pixels.
"""

from __future__ import annotations

import inspect
import os
import re
from pathlib import Path
from typing import Any

from .errors import GLUnavailable
from .runtime import get_logger

log = get_logger("gl")
_INCLUDE = re.compile(r'^\s*#include\s+"([^"]+)"\s*$', re.M)
APT_HINT = "install Mesa's EGL/GL drivers: apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1"


def create_context(require: int = 430) -> Any:
    """A standalone, headless moderngl context (GL ≥ 4.3 core). Records the route taken in
    ``ctx.extra["route"]`` ("egl" or "osmesa")."""
    import moderngl

    errors = []
    forced = os.environ.get("PCRELIGHT_GL_BACKEND", "").lower()  # "egl" or "osmesa" forces one route
    device = os.environ.get("PCRELIGHT_EGL_DEVICE", "").strip()
    if forced != "osmesa":
        try:
            ctx = moderngl.create_context(standalone=True, backend="egl", require=require,
                                          **({"device_index": int(device)} if device.isdigit() else {}))
            ctx.extra = {"route": "egl"}
            return ctx
        except Exception as e:  # noqa: BLE001 - every failure is reported below
            errors.append(f"EGL: {str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__}")
    if forced == "egl":
        raise GLUnavailable(f"no headless OpenGL context ({'; '.join(errors)}); {APT_HINT}")
    try:
        ctx = _osmesa_context(require)
        ctx.extra = {"route": "osmesa"}
        return ctx
    except Exception as e:  # noqa: BLE001
        errors.append(f"OSMesa: {str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__}")
    raise GLUnavailable(f"no headless OpenGL {require // 100}.{require % 100 // 10} context ({'; '.join(errors)}); {APT_HINT}")


def _osmesa_context(require: int) -> Any:
    """OSMesa through PyOpenGL (``PYOPENGL_PLATFORM=osmesa``), attached by moderngl."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
    try:
        from OpenGL import GL, osmesa  # type: ignore[import-not-found]
    except ImportError as e:
        raise RuntimeError("PyOpenGL with libosmesa6 is needed for the OSMesa fallback") from e
    import ctypes
    import ctypes.util

    import moderngl

    attrs = (ctypes.c_int * 11)(osmesa.OSMESA_FORMAT, osmesa.OSMESA_RGBA, osmesa.OSMESA_PROFILE,
                                osmesa.OSMESA_CORE_PROFILE, osmesa.OSMESA_CONTEXT_MAJOR_VERSION, require // 100,
                                osmesa.OSMESA_CONTEXT_MINOR_VERSION, require % 100 // 10, 0, 0, 0)
    c = osmesa.OSMesaCreateContextAttribs(attrs, None)
    if not c:
        raise RuntimeError("OSMesaCreateContextAttribs failed")
    buf = (ctypes.c_ubyte * (4 * 4 * 4))()
    if not osmesa.OSMesaMakeCurrent(c, buf, GL.GL_UNSIGNED_BYTE, 4, 4):
        raise RuntimeError("OSMesaMakeCurrent failed")
    lib = ctypes.CDLL(ctypes.util.find_library("OSMesa") or "libOSMesa.so.8")
    get = ctypes.cast(lib.OSMesaGetProcAddress, ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_char_p))

    class _Loader:  # moderngl's loader protocol: load_opengl_function(name) -> address
        def load_opengl_function(self, name: str) -> int:
            return get(name.encode()) or 0

        def __enter__(self):
            return None

        def __exit__(self, *args):
            return None

        def release(self):
            return None

    moderngl.init_context(_Loader())
    ctx = moderngl.get_context()
    ctx._osmesa = (c, buf)  # keep the context and its buffer alive
    return ctx


def context_info(ctx: Any) -> dict[str, Any]:
    """Vendor, renderer, version and route of a context, for logs and stats.json."""
    info = ctx.info
    return {
        "vendor": info.get("GL_VENDOR"),
        "renderer": info.get("GL_RENDERER"),
        "version": info.get("GL_VERSION"),
        "glsl": info.get("GL_SHADING_LANGUAGE_VERSION"),
        "route": getattr(ctx, "extra", {}).get("route", "?") if isinstance(getattr(ctx, "extra", None), dict) else "?",
        "max_ssbo_bytes": info.get("GL_MAX_SHADER_STORAGE_BLOCK_SIZE"),
    }


def bind_dummy_framebuffer(ctx: Any, size: tuple[int, int] = (1, 1)) -> Any:
    """Bind the context's tiny framebuffer (needed before draws and transform feedback on EGL), made once per
    context and size and kept in ``ctx.extra``: it lives as long as the context, callers do not release it.
    (One made and released per call left the context bound to a deleted name, and the next framebuffer moderngl
    made — it rebinds the current one — raised GL_INVALID_OPERATION: a second relight on a worker's context.)"""
    if not isinstance(ctx.extra, dict):
        ctx.extra = {}
    key = ("pcrelight_dummy_fbo", tuple(size))
    fbo = ctx.extra.get(key)
    if fbo is None:
        fbo = ctx.extra[key] = ctx.framebuffer(color_attachments=[ctx.renderbuffer(size, components=4)])
    fbo.use()
    return fbo


def load_glsl(name: str, here: str | os.PathLike | None = None, _seen: tuple[str, ...] = ()) -> str:
    """Read ``name`` from the folder of ``here`` (default: the calling module's file), replacing
    ``#include "other.glsl"`` lines by that file's text (recursively, once per file)."""
    if here is None:
        here = inspect.stack()[1].filename
    folder = Path(here).resolve()
    folder = folder if folder.is_dir() else folder.parent
    path = folder / name
    if not path.exists():
        raise FileNotFoundError(f"GLSL file not found: {path}")
    if str(path) in _seen:
        return ""
    src = path.read_text()

    def repl(m: re.Match) -> str:
        return f"// begin {m.group(1)}\n" + load_glsl(m.group(1), folder, _seen + (str(path),)) + f"\n// end {m.group(1)}\n"

    return _INCLUDE.sub(repl, src)


def _src(s: str | None, here: str, defines: dict[str, Any] | None = None) -> str | None:
    """Source of a ``.glsl`` file name (or the string itself) with ``defines`` inserted after #version."""
    if s is None:
        return None
    src = load_glsl(s, here) if s.endswith(".glsl") else s
    if defines:
        lines = src.split("\n", 1)
        src = lines[0] + "\n" + "".join(f"#define {k} {v}\n" for k, v in defines.items()) + (lines[1] if len(lines) > 1 else "")
    return src


def make_program(ctx: Any, vertex: str, fragment: str | None = None, geometry: str | None = None,
                 varyings: tuple[str, ...] = (), here: str | os.PathLike | None = None,
                 varyings_capture_mode: str = "interleaved", defines: dict[str, Any] | None = None) -> Any:
    """A program from ``.glsl`` file names (relative to the caller's folder) or source strings;
    ``defines`` are inserted after #version in every stage."""
    if here is None:
        here = inspect.stack()[1].filename
    return ctx.program(vertex_shader=_src(vertex, str(here), defines), fragment_shader=_src(fragment, str(here), defines),
                       geometry_shader=_src(geometry, str(here), defines), varyings=varyings,
                       varyings_capture_mode=varyings_capture_mode)


def make_compute(ctx: Any, name: str, here: str | os.PathLike | None = None, defines: dict[str, Any] | None = None) -> Any:
    """A compute shader from a ``.glsl`` file beside the caller; ``defines`` are inserted after #version."""
    if here is None:
        here = inspect.stack()[1].filename
    return ctx.compute_shader(_src(name, str(here), defines))


def smoke_test(ctx: Any) -> dict[str, Any]:
    """Check drawing and geometry shader + transform feedback work on ``ctx``.

    Draws the triangle (−1,−1), (1,−1), (−1,1) into an 8×8 FBO: exactly the 28 pixels whose
    centres satisfy i + j < 7 are covered (the diagonal passes through pixel corners, never through
    a centre). Then runs a geometry shader that emits k points per input point under transform
    feedback and reads the count and values back.
    """
    import numpy as np

    here = Path(__file__).parent
    fbo = ctx.framebuffer(color_attachments=[ctx.texture((8, 8), 4, dtype="f4")])
    fbo.use()
    fbo.clear(0, 0, 0, 0)
    prog = make_program(ctx, "smoke_tri.vert.glsl", "smoke_tri.frag.glsl", here=here)
    vbo = ctx.buffer(np.array([-1, -1, 1, -1, -1, 1], dtype="f4").tobytes())
    ctx.vertex_array(prog, [(vbo, "2f", "in_pos")]).render()
    px = np.frombuffer(fbo.read(components=4, dtype="f4"), dtype="f4").reshape(8, 8, 4)
    lit = int(np.count_nonzero(px[:, :, 0] > 0.5))

    k, n = 5, 7
    gs = make_program(ctx, "smoke_gs.vert.glsl", geometry="smoke_gs.geom.glsl", varyings=("out_val",), here=here)
    src = ctx.buffer(np.arange(n, dtype="f4").tobytes())
    dst = ctx.buffer(reserve=4 * n * k)
    vao = ctx.vertex_array(gs, [(src, "f", "in_val")])
    gs["k"].value = k
    q = ctx.query(primitives=True)
    with q:
        vao.transform(dst, mode=ctx.POINTS, vertices=n)
    vals = np.frombuffer(dst.read(), dtype="f4")
    return {"triangle_pixels": lit, "tf_primitives": int(q.primitives), "tf_expected": n * k,
            "tf_values_ok": bool(np.array_equal(vals, np.repeat(np.arange(n, dtype="f4"), k) * 10 + np.tile(np.arange(k), n))),
            "error": ctx.error}


def set_uniforms(prog: Any, **values: Any) -> None:
    """Set the uniforms ``values`` of a moderngl program; a name the compiler optimised out is skipped."""
    for k, v in values.items():
        try:
            prog[k].value = v
        except KeyError:  # optimised out
            pass
