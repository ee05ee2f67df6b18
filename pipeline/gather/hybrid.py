"""Hybrid PBGI (paper 000 §5.2.2): the mipmapped traversal stops at nodes smaller than Ω_tr and hands
their sub-trees to the classic walk of every receiver below."""

from __future__ import annotations

from .mipmapped import MipmappedGatherer


class HybridGatherer(MipmappedGatherer):
    """Mipmapped cut with hand-offs at Ω(A) < Ω_tr (``GatherParams.omega_tr`` × Ω_pix)."""

    HYBRID = True
