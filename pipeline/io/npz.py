"""Stage files: NPZ holding a schema string (:mod:`pipeline.schemas`), byte-deterministic, read without
pickles and without allocating what a header merely declares."""

from __future__ import annotations

import io as _io
import struct
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from .common import PathLike, atomic_path, first_line, must_exist


def check_arrays(where: PathLike, schema: str, arrays: dict[str, np.ndarray],
                 only: frozenset[str] | None = None) -> None:
    """InputError unless ``arrays`` are the schema's keys with its dtypes and shapes (``only``: of those keys, the
    others neither required nor checked)."""
    from ..schemas import SCHEMAS

    if schema not in SCHEMAS:
        raise InputError(where, f"unknown schema '{schema}'")
    spec = SCHEMAS[schema]
    sizes: dict[str, int] = {}
    extra = sorted(set(arrays) - set(spec) - {"schema"})
    if extra:
        raise InputError(where, f"schema {schema}: unexpected key(s) {', '.join(extra)}")
    for key, entry in spec.items():
        dtype, shape = entry[0], entry[1]
        optional = len(entry) > 2 and entry[2] in ("optional", "derived") or (only is not None and key not in only)
        if key not in arrays:
            if optional:
                continue
            raise InputError(where, f"schema {schema}: missing key '{key}'")
        a = np.asarray(arrays[key])
        if dtype == "str":
            ok = a.dtype.kind == "U"
        elif dtype.startswith("void"):
            ok = a.dtype.kind == "V" and a.dtype.itemsize == int(dtype[4:])
        else:
            ok = a.dtype == np.dtype(dtype)
        if not ok:
            raise InputError(where, f"schema {schema}: '{key}' has dtype {a.dtype}, expected {dtype}")
        if len(shape) != a.ndim:
            raise InputError(where, f"schema {schema}: '{key}' has shape {a.shape}, expected {shape}")
        for dim, s in zip(shape, a.shape):
            if dim is None:
                continue
            if isinstance(dim, int):
                if dim != s:
                    raise InputError(where, f"schema {schema}: '{key}' has shape {a.shape}, expected {shape}")
            elif sizes.setdefault(dim, s) != s:
                raise InputError(where, f"schema {schema}: '{key}' has {dim}={s}, but another key has {dim}={sizes[dim]}")


def write_npz(path: PathLike, schema: str, **arrays: Any) -> None:
    """Write a compressed NPZ holding ``schema`` and the arrays, validated against the registry.

    Byte-deterministic (fixed zip timestamps, sorted keys), unlike ``numpy.savez``.
    """
    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    check_arrays(path, schema, arrays)
    arrays["schema"] = np.asarray(schema)
    with atomic_path(path) as tmp:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as zf:
            for key in sorted(arrays):
                buf = _io.BytesIO()
                a = arrays[key]  # (np.ascontiguousarray would turn a 0-d array into shape (1,))
                np.lib.format.write_array(buf, a if a.flags.c_contiguous else a.copy(order="C"), allow_pickle=False)
                info = zipfile.ZipInfo(key + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.compress_type = zipfile.ZIP_DEFLATED
                info.external_attr = 0o644 << 16
                zf.writestr(info, buf.getvalue())


def _load_npz(p: Path, only: frozenset[str] | None = None) -> dict[str, np.ndarray]:
    """Every ``.npy`` member of an NPZ (``only``: those of these names), refusing pickles and arrays whose header
    declares more bytes than the member holds (before allocating them); any fault of the archive is an
    InputError."""
    import zlib

    fmt = np.lib.format
    arrays: dict[str, np.ndarray] = {}
    try:
        with zipfile.ZipFile(p) as zf:
            for info in zf.infolist():
                if not info.filename.endswith(".npy"):
                    raise InputError(p, f"not a readable NPZ file (member '{info.filename[:80]}' is not a .npy array)")
                if only is not None and info.filename[:-4] not in only:
                    continue
                with zf.open(info) as fh:
                    version = fmt.read_magic(fh)
                    if version not in ((1, 0), (2, 0), (3, 0)):
                        raise InputError(p, f"not a readable NPZ file ('{info.filename[:80]}': .npy version {version})")
                    shape, _, dtype = (fmt.read_array_header_1_0(fh) if version == (1, 0) else fmt.read_array_header_2_0(fh))
                if dtype.hasobject:
                    raise InputError(p, f"'{info.filename[:-4]}' holds Python objects (pickles are not read)")
                need = int(np.prod(shape, dtype=object)) * dtype.itemsize
                if need > info.file_size:
                    raise InputError(p, f"not a readable NPZ file ('{info.filename[:-4]}' declares {need} bytes, "
                                        f"holds {info.file_size})")
                with zf.open(info) as fh:
                    arrays[info.filename[:-4]] = fmt.read_array(fh, allow_pickle=False)
    except InputError:
        raise
    except (zipfile.BadZipFile, zlib.error, ValueError, OSError, EOFError, KeyError, NotImplementedError, RuntimeError,
            OverflowError, TypeError, struct.error, UnicodeDecodeError, MemoryError) as e:  # zipfile/numpy raise many kinds
        raise InputError(p, f"not a readable NPZ file ({type(e).__name__}: {first_line(e)})") from None
    return arrays


def read_npz(path: PathLike, schema: str, keys: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
    """Read an NPZ and validate its ``schema`` string, keys, dtypes and shapes. ``keys``: only these members are
    read and checked (relight reads 3 of bsh.npz's 21: its nodes, splat radii and emitters)."""
    p = must_exist(path)
    only = None if keys is None else frozenset(keys) | {"schema"}
    if only is not None and schema == "pcrelight.bsh/1":
        from ..bsh.format import DERIVED_KEYS

        if only & set(DERIVED_KEYS):   # computed from these (and returned with them)
            only |= {"nodes", "count"}
    arrays = _load_npz(p, only)
    if "schema" not in arrays:
        raise InputError(p, f"no 'schema' key (expected '{schema}')")
    got = str(arrays.pop("schema"))
    if got != schema:
        raise InputError(p, f"schema is '{got}', expected '{schema}'")
    check_arrays(p, schema, arrays, only)
    if schema == "pcrelight.bsh/1":    # the members build-bsh leaves to the node records (schemas: "derived")
        from ..bsh.format import with_derived

        arrays = with_derived(arrays, str(p), only)
    return arrays
