"""The disk cache of derived data paid once (the object's BSH, a lit object, a read mesh): where it lives, its
entries' names (digests of everything they are computed from) and their reads and writes."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable

from ..errors import OutputError
from ..runtime import get_logger
from .common import atomic_path


CACHE_ENV = "PCRELIGHT_CACHE_DIR"   # where derived data paid once is kept (a folder, or "off")


def cache_dir(kind: str) -> Path | None:
    """The folder for cached ``kind`` data (created on first use), or None when caching is off: ``$PCRELIGHT_CACHE_DIR``
    (``off`` turns it off), else ``$XDG_CACHE_HOME/pcrelight``, else ``~/.cache/pcrelight``; None too where it cannot
    be made (a read-only home). Entries are named by a digest of everything they are computed from, so a stale
    entry is never read; deleting the folder only costs the time to compute them again."""
    env = os.environ.get(CACHE_ENV)
    if env and env.strip().lower() in ("off", "0", "no", "none"):
        return None
    try:
        base = Path(env) if env else Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "pcrelight"
        d = base / kind
        d.mkdir(parents=True, exist_ok=True)
        return d
    except (OSError, RuntimeError, KeyError):   # Path.home() without $HOME or a passwd entry: RuntimeError/KeyError
        return None


CACHE_MAX_BYTES = 2 * 2 ** 30   # a cache folder's size (each kind's): past it the least recently used entries go


def cache_read(path: Path) -> dict | None:
    """The arrays of the cache entry ``path`` (an npz, no pickles), or None where it is missing or unreadable (the
    caller then computes it again). A read marks the entry used (its mtime: :func:`cache_write` removes the least
    recently used entries first)."""
    import numpy as np

    try:
        with np.load(path, allow_pickle=False) as z:
            out = {k: z[k] for k in z.files}
    except (OSError, ValueError, KeyError, EOFError):
        return None
    try:
        os.utime(path)
    except OSError:
        pass
    return out


def cache_write(path: Path, arrays: dict) -> None:
    """Write the cache entry ``path``: the arrays as an uncompressed npz, atomically (``io.atomic_path``); a full or
    read-only cache folder is logged (debug) and skipped. Then the folder's least recently used entries are removed
    while it holds more than :data:`CACHE_MAX_BYTES`."""
    import numpy as np

    try:
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, **arrays)
    except OutputError as e:
        get_logger("cache").debug("not cached: %s", e)
        return
    entries = []
    for f in Path(path).parent.glob("*.npz"):
        try:
            st = f.stat()
            entries.append((st.st_mtime, st.st_size, f))
        except OSError:
            pass
    total = sum(e[1] for e in entries)
    for _, size, f in sorted(entries, key=lambda e: e[0]):   # the least recently used first, never the new one
        if total <= CACHE_MAX_BYTES:
            break
        if f != Path(path):
            try:
                f.unlink()
                total -= size
            except OSError:
                pass


def content_digest(*items: object) -> str:
    """Hex blake2b digest of ``items`` in order: numpy arrays (dtype, shape and bytes), bytes, strings, numbers,
    None, and lists/tuples/dicts of them (dict keys sorted) — a cache entry's name (:func:`cache_dir`)."""
    import hashlib

    import numpy as np

    h = hashlib.blake2b(digest_size=32)

    def add(x: object) -> None:
        if isinstance(x, np.ndarray):
            a = np.ascontiguousarray(x)
            h.update(f"<array {a.dtype.descr} {a.shape}>".encode())      # descr: a record's fields and offsets too
            h.update(a.reshape(-1).view(np.uint8).data if a.size else b"")
        elif isinstance(x, (bytes, bytearray, memoryview)):
            h.update(b"<bytes %d>" % len(x))
            h.update(x)
        elif isinstance(x, dict):
            h.update(b"<dict %d>" % len(x))
            for k in sorted(x, key=str):
                add(str(k))
                add(x[k])
        elif isinstance(x, (list, tuple)):
            h.update(b"<seq %d>" % len(x))
            for v in x:
                add(v)
        else:
            h.update(f"<{type(x).__name__} {x!r}>".encode())

    for item in items:
        add(item)
    return h.hexdigest()


def code_digest(names: Iterable[str] | None = None, packages: Iterable[str] = ("numpy", "numba")) -> str:
    """Hex digest of pipeline's sources ``names`` (paths relative to ``pipeline/``; None = every ``.py`` and ``.glsl``
    file there) and of the ``packages``' versions (their version module's bytes, found without importing them): a
    cache entry computed by other code is never read."""
    import importlib.util

    root = Path(__file__).resolve().parents[1]
    files = sorted(root.rglob("*.py")) + sorted(root.rglob("*.glsl")) if names is None else [root / n for n in names]
    versions = []
    for name in packages:
        spec = importlib.util.find_spec(name)
        where = Path(spec.submodule_search_locations[0]) if spec and spec.submodule_search_locations else None
        found = [where / f for f in ("version.py", "_version.py")] if where is not None else []
        versions.append((name, next((f.read_bytes() for f in found if f.exists()), None)))
    return content_digest(versions, [(str(f.relative_to(root)), f.read_bytes()) for f in files])
