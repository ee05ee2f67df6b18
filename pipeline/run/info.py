"""``pcrelight info``: versions, GL context and capabilities, Mitsuba variant and LLVM."""

from __future__ import annotations

import importlib.metadata as md
import json
import platform
from typing import Any

PACKAGES = ["numpy", "scipy", "scikit-image", "open3d", "OpenImageIO", "colour-science", "moderngl",
            "glcontext", "click", "numba", "mitsuba", "drjit", "pyamg", "trimesh", "plyfile", "matplotlib"]


def collect() -> dict[str, Any]:
    """Everything ``info`` prints, as a dict (GL failures are recorded, not raised)."""
    from .. import __version__, gl

    data: dict[str, Any] = {"pcrelight": __version__, "python": platform.python_version(),
                            "platform": platform.platform(), "packages": {}}
    for p in PACKAGES:
        try:
            data["packages"][p] = md.version(p)
        except md.PackageNotFoundError:
            data["packages"][p] = None
    try:
        ctx = gl.create_context()
        g = gl.context_info(ctx)
        smoke = gl.smoke_test(ctx)
        g.update(smoke)
        g["geometry_shader_transform_feedback"] = smoke["tf_primitives"] == smoke["tf_expected"] and smoke["tf_values_ok"]
        g["draw"] = smoke["triangle_pixels"] == 28
        g["ok"] = g["geometry_shader_transform_feedback"] and g["draw"]
        ctx.release()
    except Exception as e:  # noqa: BLE001 - reported
        g = {"ok": False, "error": str(e)}
    data["gl"] = g
    data["mitsuba"] = mitsuba_info()
    return data


def mitsuba_info() -> dict[str, Any]:
    """The Mitsuba variant pcrelight uses and the LLVM Dr.Jit found (None if unusable)."""
    try:
        import drjit as dr
        import mitsuba as mi

        mi.set_variant("llvm_ad_rgb")
        llvm = ".".join(map(str, dr.detail.llvm_version()))
        return {"variant": mi.variant(), "llvm": llvm, "ok": True}
    except Exception as e:  # noqa: BLE001
        return {"variant": None, "llvm": None, "ok": False,
                "error": f"{e}; install Debian's libllvm19 (apt-get install libllvm19)"}


def format_info(d: dict[str, Any], as_json: bool = False) -> str:
    if as_json:
        return json.dumps(d, indent=2, sort_keys=True)
    g, m = d["gl"], d["mitsuba"]
    lines = [f"pcrelight {d['pcrelight']} (Python {d['python']}, {d['platform']})", "packages:"]
    lines += [f"  {k:15s} {v or 'not installed'}" for k, v in d["packages"].items()]
    if g.get("vendor"):
        lines += [f"GL: {g['vendor']} | {g['renderer']} | {g['version']} (route: {g['route']})",
                  f"  draw into FBO: {'ok' if g['draw'] else 'FAILED'} ({g['triangle_pixels']}/28 pixels)",
                  f"  geometry shader + transform feedback: {'ok' if g['geometry_shader_transform_feedback'] else 'FAILED'}"
                  f" ({g['tf_primitives']}/{g['tf_expected']} primitives)",
                  f"  max SSBO block: {g.get('max_ssbo_bytes')} bytes"]
    else:
        lines.append(f"GL: unavailable ({g.get('error')})")
    lines.append(f"Mitsuba: variant {m['variant']}, LLVM {m['llvm']}" if m["ok"] else f"Mitsuba: unusable ({m.get('error')})")
    return "\n".join(lines)
