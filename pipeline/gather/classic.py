"""Classic PBGI (paper 000 §5.2): every receiver walks the whole BSH from the root."""

from __future__ import annotations

from .walk import WalkGatherer


class ClassicGatherer(WalkGatherer):
    """The walk from the root for every receiver (no start lists), the whole budget for micro-buffers."""
