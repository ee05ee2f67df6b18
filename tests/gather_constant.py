"""A trivial gatherer added from outside pipeline/: one module, one table row (the last line).

Every receiver sees a uniform environment of radiance ``RADIANCE`` (a white furnace, no BSH walk), so a
Lambert receiver of base colour ρ reflects exactly ρ·L. Importing this module registers it as
``relight --method constant`` (import it before ``cli``, whose options read the table)."""

from __future__ import annotations

from typing import Any, Optional

import numpy as np

from pipeline.gather import GATHERERS, GatherParams, Receivers
from pipeline.runtime import Timings

RADIANCE = 2.0


class ConstantGatherer:
    """Lambert in a uniform environment: L_out = base colour × RADIANCE (exact; no GL work)."""

    def __init__(self, ctx: Any, nodes: np.ndarray, params: GatherParams, splat_radius: Optional[np.ndarray] = None,
                 emitters: Optional[np.ndarray] = None) -> None:
        if params.brdf != "lambert":
            raise ValueError("the constant gatherer is exact for Lambert only (--brdf lambert)")
        self.params = params

    def run(self, recv: Receivers, pixels: np.ndarray, shape: tuple[int, int],
            timings: Optional[Timings] = None) -> tuple[np.ndarray, dict[str, Any]]:
        rad = (np.asarray(recv.base_color, np.float32) * np.float32(RADIANCE)).astype(np.float32)
        return rad, {"tiles": 1, "tile_receivers": len(recv), "cut": {}}

    def release(self) -> None:
        pass


GATHERERS["constant"] = ConstantGatherer
