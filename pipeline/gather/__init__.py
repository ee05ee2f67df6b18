"""The PBGI gatherers of ``relight --method``: one module per method, one row per method in
:data:`GATHERERS`.

A gatherer factory is called as ``factory(ctx, nodes, params, splat_radius=None, emitters=None)`` (moderngl
context, (M,) :data:`pipeline.bsh.format.NODE_DTYPE` nodes, :class:`GatherParams`, the nodes' splat radii (M,)
[m] from bsh.npz or None = their radii, bsh.npz's emitters (E, 12) or None: discs the nodes leave out, which
the gather must add — :func:`pipeline.bsh.builder.split_emitters`) and returns a :class:`Gatherer`
(``run(recv, pixels, shape, timings) → (radiance (P,3) float32, stats)``, ``release()``). relight's
``--method`` choices and presets, evaluate's method and the bench scripts read this table.

To add a method: write ``pipeline/gather/<name>.py`` (usually a :class:`WalkGatherer` subclass that
returns start lists, or any class with ``run``/``release``) and add its row below.
"""

from __future__ import annotations

from .base import (
    BRDF_IDS, MASK_IDS, MICROBUFFER_SIDES, SOLID_ANGLE_MODES, STATS_KEYS, GatherFactory, Gatherer, GatherParams,
    Receivers,
)
from .classic import ClassicGatherer
from .envmap import EnvmapGatherer
from .hybrid import HybridGatherer
from .importance import ImportanceGatherer
from .mipmapped import MipmappedGatherer
from .walk import WalkGatherer

GATHERERS: dict[str, GatherFactory] = {
    "classic": ClassicGatherer,        # §5.2: every receiver walks from the root
    "mipmapped": MipmappedGatherer,    # §5.2.1: start lists = the cut from the G-buffer cone mip-map
    "hybrid": HybridGatherer,          # §5.2.2: mipmapped down to Ω_tr, then the classic walk
    "envmap": EnvmapGatherer,          # papers 002/004: image-based lighting from a cube map at the object's centre
    "importance": ImportanceGatherer,  # paper 001: importance-sampled cluster points projected into the micro-buffers
}
# envmap models the room's light alone (OBJECT_SURFELS = False: no self-shadowing, no bounces between the object's
# parts; relight warns). importance puts the object in its own light since 2026-12-07 (issue 45 §3; it was +24 % on
# the shipped view1 Lambert against full_*, now within 1 %: docs/relight.md).

__all__ = ["GATHERERS", "BRDF_IDS", "MASK_IDS", "MICROBUFFER_SIDES", "SOLID_ANGLE_MODES", "STATS_KEYS",
           "GatherFactory", "Gatherer", "GatherParams", "Receivers", "WalkGatherer", "ClassicGatherer",
           "MipmappedGatherer", "HybridGatherer", "EnvmapGatherer", "ImportanceGatherer"]
