"""The one registry of NPZ schemas: every stage file's keys, dtypes and shapes.

Each entry maps a key to ``(dtype, shape)`` or ``(dtype, shape, "optional")``.
``dtype`` is a numpy dtype name (``"float32"``), ``"str"`` (a unicode scalar or array) or
``"void40"`` (a structured record of 40 bytes). ``shape`` is a tuple whose items are ints,
names (the same name must be the same size within one file) or ``None`` (any size).
The file's own ``schema`` key (e.g. ``"pcrelight.cameras/1"``) is checked against the name.
"""

from __future__ import annotations

Spec = dict[str, tuple]

SCHEMAS: dict[str, Spec] = {
    # render-cubemaps → patchmatch, reproject (DESIGN stage 2)
    "pcrelight.cameras/1": {
        "K": ("float64", ("F", 3, 3)),
        "world_to_camera": ("float64", ("F", 4, 4)),
        "resolution": ("int32", ("F", 2)),
        "view": ("int32", ("F",)),
        "face": ("int32", ("F",)),
        "eye": ("float64", ("V", 3)),
    },
}


def register(name: str, spec: Spec) -> None:
    """Add a schema (used by tests that need a throw-away schema)."""
    SCHEMAS[name] = spec
