"""What every reader and writer of :mod:`pipeline.io` shares: atomic writes (:func:`atomic_path`), the
``<file>: <problem>`` checks (:func:`must_exist`, :func:`os_problem`, :func:`first_line`), file references
(SHA-256) and JSON (reports, scene.json and its checks)."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import tempfile
from glob import escape as glob_escape
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..errors import InputError, OutputError
from ..runtime import check_interrupt, get_logger

log = get_logger("io")
PathLike = str | os.PathLike


@contextlib.contextmanager
def atomic_path(path: PathLike) -> Iterator[Path]:
    """Yield a temp path beside ``path`` (same extension); on success fsync + rename over ``path``.

    On any exception (including SIGINT/SIGTERM) the temp file is removed and ``path`` is untouched.
    An OSError while making, writing or renaming the temp file (disk full, read-only folder, no
    permission) becomes :class:`~pipeline.errors.OutputError` naming ``path``.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        _remove_orphan_temps(path)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.{os.getpid()}.", suffix=f".tmp{path.suffix}", dir=path.parent)
        os.close(fd)
    except OSError as e:
        raise OutputError(path, f"cannot write ({os_problem(e)})") from None
    tmp_path = Path(tmp)
    umask = os.umask(0)
    os.umask(umask)
    try:
        os.chmod(tmp_path, 0o666 & ~umask)  # mkstemp makes 0600; outputs get the usual permissions
        yield tmp_path
        with open(tmp_path, "rb+") as f:
            os.fsync(f.fileno())
        check_interrupt()  # a stop request that arrived while writing: the previous file stays
        os.replace(tmp_path, path)
        try:  # make the rename durable
            dfd = os.open(path.parent, os.O_RDONLY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)
        except OSError:
            pass
    except BaseException as e:
        with contextlib.suppress(OSError):
            tmp_path.unlink()
        if isinstance(e, OSError):
            raise OutputError(path, f"cannot write ({os_problem(e)}); nothing written, "
                                    "the previous file (if any) is as it was") from None
        raise


def _remove_orphan_temps(path: Path) -> None:
    """Remove the temp files of earlier writes of ``path`` whose process is gone (a kill -9 cannot clean up
    after itself): ``.<stem>.<pid>.<random>.tmp<ext>`` with no process ``pid``."""
    for f in path.parent.glob(f".{glob_escape(path.stem)}.*.tmp{glob_escape(path.suffix)}"):
        pid = f.name[len(path.stem) + 2:].split(".", 1)[0]
        if not pid.isdigit() or int(pid) == os.getpid():
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            with contextlib.suppress(OSError):
                f.unlink()
                log.info("removed %s, left by an interrupted write (process %s is gone)", f, pid)
        except (PermissionError, OverflowError, ValueError):
            pass  # another user's live process, or not a pid


def os_problem(e: OSError) -> str:
    """'no space left on device', 'read-only file system', … from an OSError."""
    if e.strerror:
        return e.strerror[0].lower() + e.strerror[1:]
    return str(e).strip().splitlines()[0][:200] if str(e).strip() else type(e).__name__


def must_exist(path: PathLike) -> Path:
    p = Path(path)
    if not p.exists():
        raise InputError(p, "no such file")
    if p.is_dir():
        raise InputError(p, "is a directory, expected a file")
    return p

def sha256_of(path: PathLike) -> str:
    """The SHA-256 of a file's bytes (hex)."""
    import hashlib

    p = must_exist(path)
    h = hashlib.sha256()
    try:
        with open(p, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    except OSError as e:
        raise InputError(p, os_problem(e)) from None
    return h.hexdigest()


def file_ref(path: PathLike, folder: PathLike) -> tuple[str, str]:
    """How a stage file records an input it used: the input's path relative to ``folder`` (the folder the
    record is written in, so that a workspace moved with its inputs still resolves) and its SHA-256."""
    rel = os.path.relpath(Path(path).resolve(), Path(folder).resolve())
    return rel, sha256_of(path)


def follow_ref(folder: PathLike, rel: str, digest: str, what: str) -> Path:
    """The input a stage file recorded with :func:`file_ref` (``rel`` relative to ``folder``), checked to be
    the same bytes; else an InputError naming it (``what``: how to say which input it is)."""
    p = Path(os.path.normpath(Path(folder) / rel))
    if not p.is_file():
        raise InputError(p, f"no such file ({what}, recorded in {Path(folder)}): pass it on the command line")
    if sha256_of(p) != digest:
        raise InputError(p, f"changed since it was read ({what}; its SHA-256 differs from the one recorded in "
                            f"{Path(folder)}): rerun that stage, or pass the file on the command line to use it as it is")
    return p


def _jsonable(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    if dataclasses.is_dataclass(o):
        return dataclasses.asdict(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def write_json(path: PathLike, obj: Any) -> None:
    """Write pretty, key-sorted JSON atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=2, sort_keys=True, default=_jsonable) + "\n")


def read_json(path: PathLike) -> Any:
    """Read a JSON file. A scene (a file named ``scene.json``, or an object with a ``views`` table) is
    checked by :func:`validate_scene`, so every reader of a scene gets only sound values."""
    p = must_exist(path)
    try:
        obj = json.loads(p.read_text())
    except (ValueError, UnicodeDecodeError) as e:  # JSONDecodeError, and ints over Python's digit limit
        raise InputError(p, f"not valid JSON ({str(e).splitlines()[0][:200]})") from None
    except RecursionError:
        raise InputError(p, "not valid JSON (nested too deeply)") from None
    if p.name == "scene.json" or (isinstance(obj, dict) and isinstance(obj.get("views"), dict)):
        validate_scene(obj, p)
    return obj


def read_scene(path: PathLike) -> dict[str, Any]:
    """Read a scene.json (any file name) and check its values (:func:`validate_scene`)."""
    p = must_exist(path)
    obj = read_json(p)
    return validate_scene(obj, p)


def _json_numbers(o: Any, at: str) -> Iterator[tuple[str, float]]:
    if isinstance(o, bool) or o is None or isinstance(o, str):
        return
    if isinstance(o, (int, float)):
        yield at, float(o) if not isinstance(o, int) or abs(o) < 2 ** 1000 else math.inf
    elif isinstance(o, dict):
        for k, v in o.items():
            yield from _json_numbers(v, f"{at}.{k}" if at else str(k))
    elif isinstance(o, list):
        for i, v in enumerate(o):
            yield from _json_numbers(v, f"{at}[{i}]")


def _vec(p: Path, obj: Any, at: str, n: int) -> np.ndarray:
    """``n`` numbers (not booleans) at ``at``, as float64, or InputError."""
    if not (isinstance(obj, list) and len(obj) == n and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                            for x in obj)):
        raise InputError(p, f"{at} must be {n} numbers, got {json.dumps(obj)[:80]}")
    return np.asarray(obj, np.float64)


def validate_scene(obj: Any, path: PathLike) -> dict[str, Any]:
    """Check the values of a scene.json that the stages use; raise InputError naming the entry.

    Every number finite (but make-scene's ``precision`` reports); each view's ``eye``/``target``/``up`` present, three numbers, eye ≠ target, ``up`` not
    zero, ``fov_deg`` in (0, 180), ``size`` two integers in 1..16384; the
    objects' ``file`` a name, ``to_world`` an invertible 4×4 matrix, ``radius`` > 0; meshes' ``albedo`` in
    [0, 1] and ``emission`` ≥ 0; materials' ``roughness`` in [0, 1]; lamps' and the sun's radiance ≥ 0.
    """
    p = Path(path)
    if not isinstance(obj, dict):
        raise InputError(p, f"not a scene.json object (the file holds a JSON {type(obj).__name__})")
    for at, x in _json_numbers(obj, ""):
        if "precision" in at.replace("[", ".").split("."):
            continue        # make-scene's sampling report (rel_se_max is inf where no target was set): not an input
        if not math.isfinite(x):
            raise InputError(p, f"{at} is {x} (every number must be finite)")
    views = obj.get("views", {})
    if not isinstance(views, dict):
        raise InputError(p, "views must be an object of named views")
    for name, v in views.items():
        at = f"views.{name}"
        if not isinstance(v, dict):
            raise InputError(p, f"{at} must be an object with eye, target, up")
        missing = [k for k in ("eye", "target", "up") if k not in v]
        if missing:
            raise InputError(p, f"{at} has no {', '.join(missing)} (a view is a camera: eye, target, up)")
        vecs = {k: _vec(p, v[k], f"{at}.{k}", 3) for k in ("eye", "target", "up")}
        with np.errstate(all="ignore"):  # (huge finite values overflow the norm: still not zero)
            same_point = "eye" in vecs and "target" in vecs and not np.linalg.norm(vecs["target"] - vecs["eye"]) > 0
            up_zero = "up" in vecs and not np.linalg.norm(vecs["up"]) > 0
        if same_point:
            raise InputError(p, f"{at}: eye and target are the same point")
        if up_zero:
            raise InputError(p, f"{at}.up must be a non-zero vector")
        if "fov_deg" in v:
            f = v["fov_deg"]
            if isinstance(f, bool) or not isinstance(f, (int, float)) or not 0 < f < 180:
                raise InputError(p, f"{at}.fov_deg must be in (0, 180) degrees, got {f!r}")
        if "size" in v:
            sz = v["size"]
            if not (isinstance(sz, list) and len(sz) == 2 and all(type(x) is int and 1 <= x <= 16384 for x in sz)):
                raise InputError(p, f"{at}.size must be two integers in 1..16384 (width, height), got {json.dumps(sz)[:80]}")
    for key in ("object", "object2"):
        o = obj.get(key)
        if o is None:
            continue
        if not isinstance(o, dict):
            raise InputError(p, f"{key} must be an object")
        for k in ("file", "obj", "ply"):
            if k in o and not (isinstance(o[k], str) and o[k].strip()):
                raise InputError(p, f"{key}.{k} must be a file name, got {json.dumps(o[k])[:80]}")
        if "to_world" in o:
            m = o["to_world"]
            if not (isinstance(m, list) and len(m) == 4):
                raise InputError(p, f"{key}.to_world must be a 4×4 matrix (4 rows of 4 numbers)")
            M = np.stack([_vec(p, r, f"{key}.to_world[{i}]", 4) for i, r in enumerate(m)])
            if not abs(np.linalg.det(M[:3, :3])) > 1e-12:
                raise InputError(p, f"{key}.to_world is singular (a zero scale flattens the object)")
        if "radius" in o and not (isinstance(o["radius"], (int, float)) and o["radius"] > 0):
            raise InputError(p, f"{key}.radius must be > 0, got {o['radius']!r}")
        if "center" in o:
            _vec(p, o["center"], f"{key}.center", 3)
    meshes = obj.get("meshes", [])
    for i, m in enumerate(meshes if isinstance(meshes, list) else []):
        if not isinstance(m, dict):
            continue
        if "albedo" in m:
            a = _vec(p, m["albedo"], f"meshes[{i}].albedo", 3)
            if not np.all((a >= 0) & (a <= 1)):
                raise InputError(p, f"meshes[{i}].albedo must be in [0, 1] per channel (energy conservation), "
                                    f"got {m['albedo']}")
        if "emission" in m and not np.all(_vec(p, m["emission"], f"meshes[{i}].emission", 3) >= 0):
            raise InputError(p, f"meshes[{i}].emission must be ≥ 0, got {m['emission']}")
    mats = obj.get("materials", {})
    for name, m in (mats.items() if isinstance(mats, dict) else []):
        r = m.get("roughness") if isinstance(m, dict) else None
        if r is not None and (isinstance(r, bool) or not isinstance(r, (int, float)) or not 0 <= r <= 1):
            raise InputError(p, f"materials.{name}.roughness must be in [0, 1], got {r!r}")
    for key in ("lamps", "sun"):
        o = obj.get(key)
        if isinstance(o, dict):
            if "radiance" in o and not np.all(_vec(p, o["radiance"], f"{key}.radiance", 3) >= 0):
                raise InputError(p, f"{key}.radiance must be ≥ 0, got {o['radiance']}")
            if "radius" in o and not (isinstance(o["radius"], (int, float)) and o["radius"] > 0):
                raise InputError(p, f"{key}.radius must be > 0, got {o['radius']!r}")
    return obj

def first_line(e: BaseException) -> str:
    t = str(e).strip()
    return t.splitlines()[0][:200] if t else "no detail"
