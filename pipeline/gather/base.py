"""What every gatherer shares: its parameters (:class:`GatherParams`), its receivers
(:class:`Receivers`) and its interface (:class:`Gatherer`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Optional, Protocol

import numpy as np

from ..runtime import Timings

BRDF_IDS = {"lambert": 0, "ggx": 1, "disney": 2}             # eq9.comp.glsl brdf_kind
MASK_IDS = {"height-correlated": 0, "separable": 1}         # GGX Smith masking
SOLID_ANGLE_MODES = ("exact", "paper")                      # texel_table modes
MICROBUFFER_SIDES = (8, 16, 24, 32)                         # supported m


@dataclass(frozen=True)
class GatherParams:
    """Parameters of a gather, typed and with units; derived values computed once here.

    ``m`` micro-buffer side [texels]; ``stop_multiple`` k of the stop rule Ω(A) ≤ k·Ω_pix (§5.3);
    ``omega_tr`` the hybrid hand-off threshold as a multiple of Ω_pix (§5.2.2); ``memory_budget_bytes``
    GPU memory for micro-buffers, start lists and the cut's transform-feedback buffers [bytes];
    ``solid_angle`` exact|paper (see :func:`pipeline.gather.walk.texel_table`); ``brdf`` lambert|ggx|disney;
    ``masking`` GGX Smith masking; ``splat_lambda`` splat depth λ; ``lobe_samples`` n×n VNDF samples;
    ``lobe_texels`` VNDF when α·m < this; ``disc_cone`` [rad] flat-node threshold (-1 = spheres only);
    ``point_fallback`` splat sub-texel nodes into the texel of their centre; ``object_first`` the index of
    the first node of the receiving object's surfels in the node array (:func:`pipeline.relight.surfels.merge_nodes`;
    -1 = none: the paper's gather, the object absent from its own micro-buffers); ``object_near`` the near-field
    rule's height above a receiver's tangent plane below which an object leaf is not splatted [its splat radii],
    ``object_reach`` the distance from the receiver within which that rule holds [its splat radii] (its own surfel
    and its neighbours; a leaf farther away occludes whatever its height: the far wall of a concave part, which
    the rule without a reach left open in a band along the horizon — the bowl room's floor 10 % too bright);
    ``lobe_m`` the side of the lobe micro-buffer of a glossy receiver (0 = none; see ``pbgi_common.glsl``
    PBGI_LOBEBUFFER), which spans ``lobe_cover``·α radians around the mirror direction (6α holds ~90 % of the
    GGX VNDF samples) and is used where that half-angle is ≤ ``lobe_max`` [rad] (wider lobes: the hemisphere's
    resolution suffices). ``object_center`` the receiving object's bounding-box centre [m] (relight sets it;
    the envmap gatherer captures its environment there; None = unknown). ``seed`` the random numbers of a
    stochastic gatherer (importance; relight's ``--seed``).
    """

    m: int
    stop_multiple: float = 4.0
    omega_tr: float = 32.0
    memory_budget_bytes: float = float(2 ** 30)
    solid_angle: str = "exact"
    brdf: str = "lambert"
    masking: str = "height-correlated"
    splat_lambda: float = 4.0
    lobe_samples: int = 32
    lobe_texels: float = 64.0
    disc_cone: float = 1.0
    point_fallback: bool = True
    object_first: int = -1
    object_near: float = 1.0
    object_reach: float = 2.0
    object_stop: float = 1.0
    lobe_m: int = 0
    lobe_cover: float = 6.0
    lobe_max: float = 0.6
    object_center: Optional[tuple[float, float, float]] = None
    seed: int = 0

    @property
    def omega_pix(self) -> float:
        """Eq. 5's Ω_pix = 2π/m² [sr], as the float32 every shader gets (the walk's rounding)."""
        return float(np.float32(2 * math.pi / (self.m * self.m)))

    def lobe_tan(self, roughness: np.ndarray) -> np.ndarray:
        """T = tan of the lobe buffer's half-angle per receiver (float32; 0 = no lobe buffer): cover·α with
        α = max(roughness², ALPHA_MIN), where the lobe buffer applies (a GGX/Disney lobe sampled by VNDF,
        α·m < lobe_texels, half-angle ≤ lobe_max)."""
        from .brdf import ALPHA_MIN

        r = np.asarray(roughness, np.float64)
        if self.lobe_m <= 0 or self.brdf == "lambert" or self.lobe_samples <= 0:
            return np.zeros(r.shape, np.float32)
        alpha = np.maximum(r * r, ALPHA_MIN)
        half = self.lobe_cover * alpha
        use = (half <= self.lobe_max) & (alpha * self.m < self.lobe_texels)
        return np.where(use, np.tan(np.minimum(half, 1.5)), 0.0).astype(np.float32)

    @property
    def omega_tr_sr(self) -> float:
        """The hybrid threshold Ω_tr = omega_tr·Ω_pix [sr]."""
        return float(self.omega_tr) * self.omega_pix


@dataclass
class Receivers:
    """Shading points (covered G-buffer pixels), float32: position (P,3) [m], unit normal (P,3) (the shading
    normal), unit direction to the eye (P,3), base colour (P,3) linear, metallic (P,), roughness (P,), and
    ``geom_normal`` (P,3) the unit geometric normal (the surface's plane: the G-buffer's face normal; None = the
    shading normal). Eq. 9 takes light only from directions above both planes (a path tracer's ray below the face
    meets the surface itself)."""

    position: np.ndarray
    normal: np.ndarray
    view: np.ndarray
    base_color: np.ndarray
    metallic: np.ndarray
    roughness: np.ndarray
    geom_normal: Optional[np.ndarray] = None

    FIELDS = ("position", "normal", "view", "base_color", "metallic", "roughness", "geom_normal")

    def __len__(self) -> int:
        return int(self.position.shape[0])

    @property
    def geometric(self) -> np.ndarray:
        """The geometric normals (P,3) float32: ``geom_normal``, or the shading normals where it is None."""
        return self.normal if self.geom_normal is None else self.geom_normal

    def take(self, idx: np.ndarray) -> "Receivers":
        """The receivers at indices ``idx``."""
        return Receivers(*(None if getattr(self, f) is None else np.ascontiguousarray(getattr(self, f)[idx])
                           for f in self.FIELDS))

    def slice(self, lo: int, hi: int) -> "Receivers":
        return Receivers(*(None if getattr(self, f) is None else getattr(self, f)[lo:hi] for f in self.FIELDS))


class Gatherer(Protocol):
    """A PBGI gather on one GL context over one BSH, built by a :data:`GatherFactory`.

    ``run`` returns the radiance (P, 3) float32 leaving each receiver towards its eye and a stats dict
    (the keys :data:`STATS_KEYS` where they apply, plus ``cut``: the cut statistics, empty if none).
    ``pixels`` (P,) are the receivers' flat row-major viewport pixels, ``shape`` (H, W) the viewport."""

    def run(self, recv: Receivers, pixels: np.ndarray, shape: tuple[int, int],
            timings: Optional[Timings] = None) -> tuple[np.ndarray, dict[str, Any]]: ...

    def release(self) -> None: ...


GatherFactory = Callable[..., Gatherer]   # (GL context, nodes, params, splat_radius=None (M,) [m] or None = node radii, emitters=None (E, 12) or None)
STATS_KEYS = ("tiles", "tile_receivers", "microbuffer_bytes", "nodes_visited", "start_nodes", "walk_passes",
              "start_list_limit_bytes", "start_list_splits", "gather_budget_bytes", "walk_iteration_budget")
