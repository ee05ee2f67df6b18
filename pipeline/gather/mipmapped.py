"""Mipmapped PBGI (paper 000 §5.2.1): the cut of every receiver found by the transform-feedback
traversal over a cone mip-map of the G-buffer (:mod:`pipeline.gather.cut`); the walk then splats each
start node without descending."""

from __future__ import annotations

from typing import Any, Optional

import numpy as np

from .base import Receivers
from .cut import make_start_lists
from .walk import StartLists, WalkGatherer


class MipmappedGatherer(WalkGatherer):
    """Start lists from :func:`pipeline.gather.cut.make_start_lists`; 3/4 of the memory budget for the
    walk (micro-buffers, start lists), 1/4 for the cut's transform-feedback buffers."""

    HYBRID = False
    GATHER_SHARE = 0.75

    def start_lists(self, recv: Receivers, pixels: np.ndarray, shape: tuple[int, int]) -> tuple[Optional[StartLists], dict[str, Any]]:
        tf_budget = int(self.params.memory_budget_bytes * (1 - self.GATHER_SHARE))
        return make_start_lists(self.ctx, recv.position, recv.normal, pixels, shape, self.node_buf, self.params,
                                self.HYBRID, tf_budget=tf_budget)
