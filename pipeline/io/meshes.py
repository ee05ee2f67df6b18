"""Triangle meshes and renderable objects: PLY / OBJ / glTF-GLB through trimesh (parts with their
metallic-roughness materials and textures), the glTF JSON for what trimesh drops, material range checks."""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path
from typing import Any

import numpy as np

from ..color import srgb_decode
from ..errors import InputError
from .common import PathLike, atomic_path, first_line, log, must_exist


def write_mesh(path: PathLike, vertices: np.ndarray, faces: np.ndarray | None = None,
               normals: np.ndarray | None = None, base_color: tuple | None = None,
               metallic: float = 0.0, roughness: float = 1.0) -> None:
    """Write a triangle mesh, format from the extension: ``.ply`` (binary little-endian, float32
    ``x y z`` [+ ``nx ny nz``], int32 ``vertex_indices``), ``.obj`` (text, ``v``/``vn``/``f``) or
    ``.glb`` (glTF 2.0 binary with one metallic-roughness material: ``base_color`` linear RGB,
    ``metallic``, ``roughness``). ``faces=None`` means a triangle soup (3 vertices a face).
    Byte-deterministic for the same arrays."""
    v = np.ascontiguousarray(vertices, dtype=np.float32)
    f = (np.arange(len(v), dtype=np.int32).reshape(-1, 3) if faces is None
         else np.ascontiguousarray(faces, dtype=np.int32))
    n = None if normals is None else np.ascontiguousarray(normals, dtype=np.float32)
    ext = Path(path).suffix.lower()
    with atomic_path(path) as tmp:
        if ext == ".ply":
            from plyfile import PlyData, PlyElement

            fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
            if n is not None:
                fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
            va = np.empty(len(v), dtype=fields)
            for i, c in enumerate("xyz"):
                va[c] = v[:, i]
                if n is not None:
                    va["n" + c] = n[:, i]
            fa = np.empty(len(f), dtype=[("vertex_indices", "<i4", (3,))])
            fa["vertex_indices"] = f
            PlyData([PlyElement.describe(va, "vertex"), PlyElement.describe(fa, "face")],
                    text=False, byte_order="<").write(str(tmp))
        elif ext == ".obj":
            lines = [f"v {a:.7g} {b:.7g} {c:.7g}" for a, b, c in v.tolist()]
            if n is not None:
                lines += [f"vn {a:.7g} {b:.7g} {c:.7g}" for a, b, c in n.tolist()]
                lines += [f"f {a}//{a} {b}//{b} {c}//{c}" for a, b, c in (f + 1).tolist()]
            else:
                lines += [f"f {a} {b} {c}" for a, b, c in (f + 1).tolist()]
            tmp.write_text("\n".join(lines) + "\n")
        elif ext == ".glb":
            import trimesh

            mat = trimesh.visual.material.PBRMaterial(
                baseColorFactor=[*(base_color if base_color is not None else (0.8, 0.8, 0.8)), 1.0],
                metallicFactor=float(metallic), roughnessFactor=float(roughness))
            tm = trimesh.Trimesh(vertices=v, faces=f, vertex_normals=n, process=False,
                                 visual=trimesh.visual.TextureVisuals(material=mat))
            tmp.write_bytes(tm.export(file_type="glb"))
        else:
            raise ValueError(f"{path}: unknown mesh format '{ext}' (use .ply, .obj or .glb)")


def read_mesh(path: PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a triangle mesh (PLY, OBJ, glTF/GLB; several meshes are merged in world space):
    ``(vertices (V,3) float32, faces (F,3) int32, vertex normals (V,3) float32)`` — normals from
    the file when present, else area-weighted from the faces."""
    import trimesh

    p = must_exist(path)
    try:
        m = trimesh.load(str(p), force="mesh", process=False)
    except Exception as e:  # trimesh raises many kinds
        raise InputError(p, f"not a readable mesh ({type(e).__name__}: {e})") from None
    if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
        raise InputError(p, "no triangles in the mesh")
    v = np.asarray(m.vertices, dtype=np.float32)
    if not np.all(np.isfinite(v)):
        raise InputError(p, "non-finite vertex positions")
    return v, np.asarray(m.faces, dtype=np.int32), np.asarray(m.vertex_normals, dtype=np.float32)


def read_object(path: PathLike, cache: bool = False) -> list[dict[str, Any]]:
    """Read a renderable object (glTF/GLB, OBJ, PLY) as a list of parts in the file's world space
    (scene-graph transforms applied), one per mesh × material. Each part: ``positions`` (V,3) f32,
    ``normals`` (V,3) f32 or None (file normals only), ``faces`` (F,3) u32, ``uv`` (V,2) f32 or None
    (as trimesh gives it: OpenGL convention, v = 0 at the image's bottom row), ``vertex_color`` (V,3) linear f32 or None
    (uchar PLY colours are sRGB-decoded), ``base_color`` (3,) linear, ``metallic``, ``roughness``
    (glTF metallic-roughness factors; OBJ: Kd, metallic 0, roughness 1; PLY: 0.8 grey),
    ``base_color_tex`` (H,W,3) linear f32 or None (sRGB-decoded), ``mr_tex`` (H,W,3) f32 or None
    (glTF: G = roughness, B = metallic, linear), ``double_sided`` bool, ``pbr`` bool (a glTF
    metallic-roughness material was present), ``emissive`` (3,) linear radiance (the pipeline's units) = glTF
    ``emissiveFactor`` × ``KHR_materials_emissive_strength`` (0 elsewhere),
    ``emissive_tex`` (H,W,3) linear f32 or None (sRGB-decoded), and per texture the KHR_texture_transform as a
    3×3 affine matrix on the ``uv`` above (trimesh's convention) or None: ``base_color_uv``, ``mr_uv``,
    ``emissive_uv``, ``normal_uv`` (:func:`uv_transformed` applies one); ``normal_tex`` (H,W,3) linear f32 or
    None (glTF tangent-space normal map, as stored in [0, 1]) and ``normal_scale``.

    ``cache``: a self-contained file (PLY, or a GLB whose buffers and images are inside it) is kept parsed in
    :func:`pipeline.io.cache.cache_dir` ("object") under a digest of its bytes, of pipeline's sources and of trimesh's,
    SciPy's and Pillow's versions, and read from there the next time: the same parts without importing trimesh
    (~0.45 CPU s of a relight); the warnings it logged are logged again."""
    if cache:
        return _read_object_cached(must_exist(path))
    return _read_object(path)


OBJECT_FORMAT = "pcrelight.object_parts/1"   # read_object's cache entries (in their digest)


def _self_contained(p: Path) -> bool:
    """Whether the object file ``p`` holds everything it is read from: a PLY, or a GLB with no external buffer or
    image (every ``uri`` a ``data:`` one)."""
    ext = p.suffix.lower()
    if ext == ".ply":
        return True
    if ext != ".glb":
        return False
    doc = _gltf_json(p)
    if not isinstance(doc, dict):
        return False
    for kind in ("buffers", "images"):
        items = doc.get(kind) or []
        if not isinstance(items, list) or not all(isinstance(x, dict) for x in items):
            return False
        if any("uri" in x and not str(x["uri"]).startswith("data:") for x in items):
            return False
    return True


def _read_object_cached(p: Path) -> list[dict[str, Any]]:
    """:func:`read_object` through the cache (its ``cache`` argument)."""
    import logging

    from .cache import cache_dir, cache_read, cache_write, code_digest, content_digest

    folder = cache_dir("object")
    if folder is None or not _self_contained(p):
        return _read_object(p)
    key = content_digest(OBJECT_FORMAT, p.suffix.lower(), p.read_bytes(),
                         code_digest(packages=("numpy", "trimesh", "scipy", "PIL")))
    entry = folder / f"{key}.npz"
    got = _parts_from_entry(cache_read(entry))
    if got is not None:
        parts, warnings = got
        for w in warnings:
            log.warning("%s", w)
        return parts
    warned: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if record.levelno >= logging.WARNING:
                warned.append(record.getMessage())

    keep = Keep()
    log.addHandler(keep)
    try:
        parts = _read_object(p)
    finally:
        log.removeHandler(keep)
    arrays = _parts_to_entry(parts, warned)
    if arrays is not None:
        cache_write(entry, arrays)
    return parts


def _parts_to_entry(parts: list[dict[str, Any]], warnings: list[str]) -> dict[str, np.ndarray] | None:
    """The parts as a cache entry's arrays (each array its own member, the rest JSON in ``meta``); None where a value
    is of a kind JSON would not give back as it was (then nothing is cached)."""
    arrays: dict[str, np.ndarray] = {}
    meta = []
    for i, part in enumerate(parts):
        m: dict[str, Any] = {}
        for k, v in part.items():
            if isinstance(v, np.ndarray):
                arrays[f"p{i}.{k}"] = v
                m[k] = {"array": f"p{i}.{k}"}
            elif v is None or type(v) in (bool, int, float, str):
                m[k] = v
            else:
                return None
        meta.append(m)
    arrays["meta"] = np.array(json.dumps({"parts": meta, "warnings": warnings}))
    return arrays


def _parts_from_entry(d: dict[str, np.ndarray] | None) -> tuple[list[dict[str, Any]], list[str]] | None:
    """(parts, warnings) of a cache entry written by :func:`_parts_to_entry`; None where it is not one."""
    if d is None or "meta" not in d:
        return None
    try:
        meta = json.loads(str(d["meta"]))
        parts = [{k: d[v["array"]] if isinstance(v, dict) else v for k, v in m.items()} for m in meta["parts"]]
        return parts, [str(w) for w in meta["warnings"]]
    except (ValueError, KeyError, TypeError):
        return None


def _read_object(path: PathLike) -> list[dict[str, Any]]:
    """:func:`read_object` without the cache."""
    import trimesh

    p = must_exist(path)
    check_materials(p)  # trimesh clips out-of-range colours silently: check the file's own values first
    gltf = _gltf_json(p) if p.suffix.lower() in (".glb", ".gltf") else None
    gmats = gltf.get("materials") if isinstance(gltf, dict) else None
    gmats = gmats if isinstance(gmats, list) and all(isinstance(m, dict) for m in gmats) else None
    try:
        loaded = _load_tagged(p, gltf) if gmats else trimesh.load(str(p), process=False)
    except Exception as e:  # trimesh raises many kinds
        raise InputError(p, f"not a readable mesh ({type(e).__name__}: {first_line(e)})") from None
    except RecursionError:
        raise InputError(p, "not a readable mesh (nested too deeply)") from None
    if isinstance(loaded, trimesh.Trimesh):
        items = [(np.eye(4), loaded)]
    elif isinstance(loaded, trimesh.Scene):
        items = []
        for node in loaded.graph.nodes_geometry:
            T, gname = loaded.graph[node]
            g = loaded.geometry.get(gname)
            if isinstance(g, trimesh.Trimesh):
                items.append((np.asarray(T, np.float64), g))
    else:
        items = []
    parts: list[dict[str, Any]] = []
    ignored: dict[str, list[str]] = {}          # glTF material features the renderer does not apply yet (issue 24)
    extra = [_gltf_material_extra(p, m, i, ignored) for i, m in enumerate(gmats or [])]

    def img(im: Any, srgb: bool) -> np.ndarray | None:
        if im is None:
            return None
        try:
            a = np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
        except Exception as e:  # PIL raises many kinds on a broken embedded image
            raise InputError(p, f"unreadable texture image ({type(e).__name__}: {first_line(e)})") from None
        if a.ndim != 3 or a.shape[0] == 0 or a.shape[1] == 0:
            raise InputError(p, "empty texture image")
        return srgb_decode(a).astype(np.float32) if srgb else a

    for T, g in items:
        if len(g.faces) == 0:
            continue
        if not np.all(np.isfinite(T)) or not abs(np.linalg.det(T[:3, :3])) > 1e-12:
            raise InputError(p, "a node's transform is singular or not finite (a zero scale flattens the mesh)")
        if np.asarray(g.vertices).ndim != 2 or np.asarray(g.vertices).shape[1] != 3:
            raise InputError(p, f"vertices are not (x, y, z) triples (shape {np.asarray(g.vertices).shape})")
        with np.errstate(all="ignore"):
            v = np.asarray(g.vertices, np.float64)
            v = (v @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
        if not np.all(np.isfinite(v)):
            raise InputError(p, "non-finite vertex positions")
        faces = np.asarray(g.faces)
        if faces.ndim != 2 or faces.shape[1] != 3 or faces.min() < 0 or faces.max() >= len(v):
            raise InputError(p, f"faces index vertices outside 0..{len(v) - 1}")
        nrm = None
        with np.errstate(all="ignore"):
            raw = np.asarray(g.vertex_normals, np.float64)  # the file's, else trimesh's from the faces
        if raw.shape == v.shape:
            if not np.all(np.isfinite(raw)):
                raise InputError(p, f"{int(np.count_nonzero(~np.isfinite(raw).all(axis=1)))} vertex normals are not finite")
            nrm = (raw @ np.linalg.inv(T[:3, :3])).astype(np.float32)  # inverse-transpose, row vectors
        part: dict[str, Any] = {"positions": v, "normals": nrm, "faces": np.asarray(g.faces, np.uint32),
                                "uv": None, "vertex_color": None, "base_color": np.array([0.8, 0.8, 0.8], np.float32),
                                "metallic": 0.0, "roughness": 1.0, "base_color_tex": None, "mr_tex": None,
                                "double_sided": False, "pbr": False, "emissive": np.zeros(3, np.float32),
                                "emissive_tex": None, "base_color_uv": None, "mr_uv": None, "emissive_uv": None,
                                "normal_tex": None, "normal_uv": None, "normal_scale": 1.0}
        vis = g.visual
        if isinstance(vis, trimesh.visual.TextureVisuals):
            mat = vis.material
            if vis.uv is not None and len(vis.uv) == len(v):
                part["uv"] = np.asarray(vis.uv, np.float32)
                if part["uv"].ndim != 2 or part["uv"].shape[1] != 2 or not np.all(np.isfinite(part["uv"])):
                    raise InputError(p, "texture coordinates are not finite (u, v) pairs")
            if isinstance(mat, trimesh.visual.material.PBRMaterial):
                part["pbr"] = True
                bc = mat.baseColorFactor
                if bc is not None:
                    part["base_color"] = (np.asarray(bc, np.float32)[:3] / 255.0).astype(np.float32)
                else:
                    part["base_color"] = np.ones(3, np.float32)
                part["metallic"] = float(1.0 if mat.metallicFactor is None else mat.metallicFactor)
                part["roughness"] = float(1.0 if mat.roughnessFactor is None else mat.roughnessFactor)
                part["double_sided"] = bool(getattr(mat, "doubleSided", False))
                part["base_color_tex"] = img(mat.baseColorTexture, True) if part["uv"] is not None else None
                part["mr_tex"] = img(mat.metallicRoughnessTexture, False) if part["uv"] is not None else None
                gi = _tag_index(mat, gmats)              # the glTF material index (None: not a glTF)
                mname = _material_name(mat, gmats) or f"#{len(parts)}"
                if gi is not None:
                    part.update(extra[gi])
                    for attr, key, srgb in (("emissiveTexture", "emissive_tex", True), ("normalTexture", "normal_tex", False)):
                        if part["uv"] is not None:
                            part[key] = img(getattr(mat, attr, None), srgb)
                        elif getattr(mat, attr, None) is not None:
                            ignored.setdefault(f"{attr} without texture coordinates", []).append(mname)
                for attr, what in (("normalTexture", "normal map"), ("occlusionTexture", "occlusion map")):
                    if attr == "normalTexture" and gi is not None:
                        continue                             # applied (a glTF's; the G-buffer's shading normal)
                    if getattr(mat, attr, None) is not None:
                        ignored.setdefault(f"{what} ({attr})", []).append(mname)
            elif mat is not None:  # OBJ/MTL SimpleMaterial
                d = getattr(mat, "diffuse", None)
                if d is not None:
                    part["base_color"] = (np.asarray(d, np.float32)[:3] / 255.0).astype(np.float32)
                im = getattr(mat, "image", None)
                part["base_color_tex"] = img(im, True) if part["uv"] is not None else None
        elif isinstance(vis, trimesh.visual.ColorVisuals) and vis.kind == "vertex":
            vc = np.asarray(vis.vertex_colors, np.float32)[:, :3] / 255.0
            part["vertex_color"] = srgb_decode(vc).astype(np.float32)
        _check_part_material(p, part, len(parts))
        parts.append(part)
    if not parts:
        raise InputError(p, "no triangles in the mesh")
    for what, mats in ignored.items():
        log.warning("%s: %s ignored (not applied yet) in material(s) %s", p, what, ", ".join(sorted(set(mats))))
    if p.suffix.lower() in (".glb", ".gltf"):
        used = (_gltf_json(p) or {}).get("extensionsUsed") or []
        for ext in sorted(e for e in used if isinstance(e, str) and e in GLTF_IGNORED_EXTENSIONS):
            log.warning("%s: glTF extension %s ignored (not applied yet: %s)", p, ext, GLTF_IGNORED_EXTENSIONS[ext])
    return parts


# glTF extensions the object reader does not apply yet (issue 24), with what that changes
# (read: KHR_texture_transform on the base-colour, metallic-roughness and emissive textures,
# KHR_materials_emissive_strength)
GLTF_IGNORED_EXTENSIONS = {
    "KHR_materials_clearcoat": "no clear coat layer", "KHR_materials_transmission": "rendered opaque",
    "KHR_materials_sheen": "no sheen", "KHR_materials_specular": "the default specular",
    "KHR_materials_ior": "the default IOR 1.5", "KHR_materials_volume": "no volume",
    "KHR_materials_iridescence": "no iridescence", "KHR_materials_anisotropy": "isotropic roughness",
}

TAG = "\x00pcrelight-material-"   # a glTF material's name while trimesh loads it (its index follows)


def _load_tagged(p: Path, doc: dict[str, Any]) -> Any:
    """trimesh's load of a glTF whose materials are renamed ``TAG<index>`` (the file is not changed: its JSON
    is edited in memory), so that each part's material is known by its glTF index (trimesh keeps the name and
    drops what :func:`_gltf_material_extra` reads); :func:`_material_name` gives the file's names back."""
    import io as _io

    import trimesh

    doc = json.loads(json.dumps(doc))
    for i, m in enumerate(doc["materials"]):
        m["name"] = f"{TAG}{i}"
    text = json.dumps(doc).encode()
    if p.suffix.lower() == ".glb" or p.read_bytes()[:4] == b"glTF":
        raw = p.read_bytes()
        clen = struct.unpack_from("<I", raw, 12)[0]
        text += b" " * (-len(text) % 4)                         # chunks are 4-byte aligned (spaces for JSON)
        rest = raw[20 + clen:]
        body = struct.pack("<II", len(text), 0x4E4F534A) + text + rest
        data = raw[:8] + struct.pack("<I", 12 + len(body)) + body
        return trimesh.load(_io.BytesIO(data), file_type="glb", process=False)
    return trimesh.load(_io.BytesIO(text), file_type="gltf", resolver=trimesh.resolvers.FilePathResolver(str(p)),
                        process=False)


def _tag_index(mat: Any, gmats: list[dict[str, Any]] | None) -> int | None:
    """The glTF index of a material loaded by :func:`_load_tagged`, else None (not a glTF)."""
    name = getattr(mat, "name", None)
    if not gmats or not isinstance(name, str) or not name.startswith(TAG):
        return None
    return int(name[len(TAG):])


def _material_name(mat: Any, gmats: list[dict[str, Any]] | None) -> str | None:
    """A material's name as the file gives it (the glTF's, not the tag :func:`_load_tagged` gave it)."""
    i = _tag_index(mat, gmats)
    if i is None:
        return getattr(mat, "name", None)
    name = gmats[i].get("name") if gmats else None
    return name if isinstance(name, str) else None


# the glTF UV convention (v = 0 at the image's top row) ↔ trimesh's (v = 0 at the bottom row): its own inverse
_FLIP_V = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 1.0], [0.0, 0.0, 1.0]])


def texture_transform(p: Path, info: Any, where: str, ignored: dict[str, list[str]]) -> np.ndarray | None:
    """The KHR_texture_transform of a glTF textureInfo as a 3×3 affine matrix on trimesh's UVs (v = 0 at the
    bottom row), or None for none (identity). The extension's matrix is T(offset) · R(rotation) · S(scale) on
    glTF UVs (the extension's GLSL, its column-major ``mat3`` read as written: R = [[cos, −sin], [sin, cos]]); a ``texCoord``
    other than 0 (in the textureInfo or the extension) is warned about: trimesh reads TEXCOORD_0 only."""
    if not isinstance(info, dict):
        return None
    ext = info.get("extensions")
    ext = ext.get("KHR_texture_transform") if isinstance(ext, dict) else None
    coord = info.get("texCoord", 0)
    if isinstance(ext, dict) and "texCoord" in ext:
        coord = ext["texCoord"]
    if coord != 0:
        ignored.setdefault(f"texture coordinate set {coord!r} (TEXCOORD_0 used instead)", []).append(where)
    if not isinstance(ext, dict):
        return None
    off = _vec_or(p, ext.get("offset"), [0.0, 0.0], f"{where}: KHR_texture_transform.offset")
    sc = _vec_or(p, ext.get("scale"), [1.0, 1.0], f"{where}: KHR_texture_transform.scale")
    rot = _vec_or(p, None if "rotation" not in ext else [ext["rotation"]], [0.0], f"{where}: KHR_texture_transform.rotation")[0]
    c, s = math.cos(rot), math.sin(rot)
    m = (np.array([[1.0, 0.0, off[0]], [0.0, 1.0, off[1]], [0.0, 0.0, 1.0]])
         @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.diag([sc[0], sc[1], 1.0]))
    m = _FLIP_V @ m @ _FLIP_V
    return None if np.array_equal(m, np.eye(3)) else m


def _vec_or(p: Path, x: Any, default: list[float], what: str) -> list[float]:
    if x is None:
        return default
    if not (isinstance(x, list) and len(x) == len(default) and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in x)):
        raise InputError(p, f"{what} must be {len(default)} finite number(s), got {json.dumps(x)[:80]}")
    return [float(v) for v in x]


def uv_transformed(uv: np.ndarray, xf: np.ndarray | None) -> np.ndarray:
    """UVs (N,2) through a part's texture transform (``base_color_uv``…; None: as they are)."""
    if xf is None:
        return uv
    return uv @ xf[:2, :2].T + xf[:2, 2]


def _gltf_material_extra(p: Path, m: dict[str, Any], i: int, ignored: dict[str, list[str]]) -> dict[str, Any]:
    """What trimesh drops of glTF material ``i``: the texture transforms and the emission (factor × strength)."""
    where = f"material {i}" + (f" ('{m['name']}')" if isinstance(m.get("name"), str) else "")
    pbr = m.get("pbrMetallicRoughness") if isinstance(m.get("pbrMetallicRoughness"), dict) else {}
    ef = np.asarray(_vec_or(p, m.get("emissiveFactor"), [0.0, 0.0, 0.0], f"{where}: emissiveFactor"))
    ext = m.get("extensions") if isinstance(m.get("extensions"), dict) else {}
    es = ext.get("KHR_materials_emissive_strength")
    strength = 1.0
    if isinstance(es, dict) and "emissiveStrength" in es:
        strength = _vec_or(p, [es["emissiveStrength"]], [1.0], f"{where}: emissiveStrength")[0]
        if strength < 0:
            raise InputError(p, f"{where}: KHR_materials_emissive_strength.emissiveStrength {strength:g} must be ≥ 0")
    nt = m.get("normalTexture") if isinstance(m.get("normalTexture"), dict) else {}
    nscale = _vec_or(p, [nt["scale"]] if "scale" in nt else None, [1.0], f"{where}: normalTexture.scale")[0]
    return {"emissive": (ef * strength).astype(np.float32), "normal_scale": nscale,
            "normal_uv": texture_transform(p, m.get("normalTexture"), where, ignored),
            "base_color_uv": texture_transform(p, pbr.get("baseColorTexture"), where, ignored),
            "mr_uv": texture_transform(p, pbr.get("metallicRoughnessTexture"), where, ignored),
            "emissive_uv": texture_transform(p, m.get("emissiveTexture"), where, ignored)}


def _check_part_material(p: Path, part: dict[str, Any], i: int) -> None:
    """The values a part's material ends up with: finite, colours and factors in [0, 1]."""
    bc = np.asarray(part["base_color"], np.float64)
    if bc.shape != (3,) or not np.all(np.isfinite(bc)) or not np.all((bc >= 0) & (bc <= 1)):
        raise InputError(p, f"part {i}: base colour {np.round(bc, 4).tolist()} is outside [0, 1] (energy conservation)")
    for k in ("metallic", "roughness"):
        x = part[k]
        if not (math.isfinite(x) and 0 <= x <= 1):
            raise InputError(p, f"part {i}: {k} {x!r} is outside [0, 1]")


def _unit(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and 0 <= x <= 1


def _gltf_json(p: Path) -> Any:
    """The JSON of a .gltf, or of a .glb's first chunk; None when the file is not laid out as one (the
    mesh reader then says what is wrong with it)."""
    raw = p.read_bytes()
    if p.suffix.lower() == ".glb" or raw[:4] == b"glTF":
        if len(raw) < 20 or raw[:4] != b"glTF":
            return None
        clen, ctype = struct.unpack_from("<II", raw, 12)
        if ctype != 0x4E4F534A or 20 + clen > len(raw):
            return None
        raw = raw[20:20 + clen]
    try:
        return json.loads(raw)
    except (ValueError, UnicodeDecodeError, RecursionError):
        return None


def check_materials(path: PathLike) -> None:
    """Check the material values an object file states (trimesh clips some silently): glTF
    ``baseColorFactor``, ``metallicFactor``, ``roughnessFactor``, ``emissiveFactor`` and
    ``occlusionTexture.strength`` in [0, 1]; OBJ/MTL ``Kd``/``Ka``/``Ks`` and ``Pr``/``Pm`` (PBR
    roughness/metallic) and ``d`` in [0, 1], ``Ke``/``Ns`` ≥ 0. Raise InputError naming the material."""
    p = Path(path)
    ext = p.suffix.lower()
    if ext in (".glb", ".gltf"):
        doc = _gltf_json(p)
        mats = doc.get("materials", []) if isinstance(doc, dict) else []
        for i, m in enumerate(mats if isinstance(mats, list) else []):
            if not isinstance(m, dict):
                raise InputError(p, f"material {i} is not a JSON object")
            name = f"material {i}" + (f" ('{m['name']}')" if isinstance(m.get("name"), str) else "")
            pbr = m.get("pbrMetallicRoughness", {})
            if not isinstance(pbr, dict):
                raise InputError(p, f"{name}: pbrMetallicRoughness is not a JSON object")
            bc = pbr.get("baseColorFactor")
            if bc is not None and not (isinstance(bc, list) and len(bc) == 4 and all(_unit(x) for x in bc)):
                raise InputError(p, f"{name}: baseColorFactor {json.dumps(bc)[:80]} must be 4 numbers in [0, 1] "
                                    "(energy conservation: a surface reflects at most the light it receives)")
            for k in ("metallicFactor", "roughnessFactor"):
                if k in pbr and not _unit(pbr[k]):
                    raise InputError(p, f"{name}: {k} {json.dumps(pbr[k])[:40]} must be in [0, 1]")
            ef = m.get("emissiveFactor")
            if ef is not None and not (isinstance(ef, list) and len(ef) == 3 and all(_unit(x) for x in ef)):
                raise InputError(p, f"{name}: emissiveFactor {json.dumps(ef)[:80]} must be 3 numbers in [0, 1]")
            occ = m.get("occlusionTexture")
            if isinstance(occ, dict) and "strength" in occ and not _unit(occ["strength"]):
                raise InputError(p, f"{name}: occlusionTexture.strength must be in [0, 1]")
    elif ext == ".obj":
        try:
            text = p.read_text(errors="replace")
        except OSError as e:
            raise InputError(p, f"cannot read ({e.strerror})") from None
        for line in text.splitlines():
            w = line.split(None, 1)
            if len(w) == 2 and w[0] == "mtllib":
                for lib in w[1].split():
                    mtl = p.parent / lib
                    if mtl.is_file():
                        _check_mtl(mtl)


def _check_mtl(mtl: Path) -> None:
    rules = {"Kd": (0, 1, "diffuse colour"), "Ka": (0, 1, "ambient colour"), "Ks": (0, 1, "specular colour"),
             "Pr": (0, 1, "roughness"), "Pm": (0, 1, "metallic"), "d": (0, 1, "opacity"),
             "Ke": (0, math.inf, "emission"), "Ns": (0, math.inf, "specular exponent")}
    name = "?"
    for n, line in enumerate(mtl.read_text(errors="replace").splitlines(), 1):
        w = line.split()
        if not w:
            continue
        if w[0] == "newmtl":
            name = " ".join(w[1:])
            continue
        if w[0] not in rules or (len(w) > 1 and w[1] == "spectral") or (len(w) > 1 and w[1] == "xyz"):
            continue
        lo, hi, what = rules[w[0]]
        try:
            vals = [float(x) for x in w[1:]]
        except ValueError:
            raise InputError(mtl, f"line {n}: material '{name}': {w[0]} must be numbers, got {' '.join(w[1:])[:60]!r}") from None
        if not vals or not all(math.isfinite(x) and lo <= x <= hi for x in vals):
            rng = f"in [{lo}, {hi}]" if hi != math.inf else f"≥ {lo}"
            raise InputError(mtl, f"line {n}: material '{name}': {w[0]} ({what}) {' '.join(w[1:])[:60]} must be {rng}"
                                  + (" (energy conservation)" if w[0] in ("Kd", "Ka", "Ks") else ""))
