"""make setup's numba warm-up (pipeline/run/warm.py, issue 46): it runs, and it leaves build-bsh's kernels in numba's
on-disk cache, so that the first real build-bsh loads them instead of compiling (measured: 95 s → 5.7 s on the
shipped cloud, docs/bench/bsh.md)."""

from __future__ import annotations

from pathlib import Path

import pipeline.bsh.tree as tree
from pipeline.run.warm import warm


def test_warm_runs_and_caches_the_bsh_kernels():
    parts = warm()
    assert set(parts) == {"build-bsh", "splats", "patchmatch"} and all(v >= 0 for v in parts.values())
    cache = Path(tree.__file__).parent / "__pycache__"
    indexed = {f.name.split(".")[1].split("-")[0] for f in cache.glob("tree.*.nbi")}
    # every @njit kernel of tree.py that build-bsh runs has its index file
    assert {"_block_runs"} <= indexed and len(indexed) >= 20, sorted(indexed)
