"""poisson (seed 000 §4.2, Eq. 2–3): HDR colours for the points that have none.

Unknowns Ω: exactly the points with ``valid == 0`` in the input cloud — after ``reproject`` these are
the overexposed points (LDR luminance > t_l) that no face saw or whose every sample had Q > t_h.
Every other point (``valid == 1``, or a cloud without ``valid``) is known: its colour H(q) is used as
is.  The known neighbours of Ω are ∂Ω.

Graph: the k = 16 nearest neighbours of every point (scipy cKDTree, the point itself excluded),
**symmetrised by union**: q ∈ N_p ⇔ q ∈ kNN(p) or p ∈ kNN(q).  Union keeps every kNN edge and
makes the system matrix symmetric (so CG/AMG and a symmetric factorisation apply).

Equation 2 for every p ∈ Ω, with guidance v_pq = L(p) − L(q) (Eq. 3, L the LDR colour):
    |N_p| H(p) − Σ_{q∈N_p∩Ω} H(q) = Σ_{q∈N_p∩∂Ω} H(q) + Σ_{q∈N_p} v_pq
i.e. (D − W_ΩΩ) H_Ω = W_Ω∂ H_∂ + (D L − W L)_Ω: a symmetric, weakly diagonally dominant sparse matrix,
positive definite on every connected component of Ω (in the graph restricted to Ω) that has at
least one edge to ∂Ω.  Its solution is H = L + h with h discrete-harmonic on Ω and h = H − L on ∂Ω.

Rim (``rim``, not in the paper): with ``dirichlet`` every known neighbour is a boundary value, so an
overexposed region's excess over LDR falls harmonically to 0 at its unsaturated rim — but a saturated
region is saturated because it is brighter than the clip everywhere (a sunlit patch, a lamp's face):
its true values do not fall towards the rim.  ``free`` (default) cuts Ω's edges to kept-LDR points
(``source`` 0: the unsaturated rim, and overexposed points kept at LDR) — a no-flux (Neumann) rim —
so Ω is filled from its projected neighbours only: flat where one value was seen, harmonic between
several; a region with no projected point has no boundary and keeps its LDR colour (a lower bound).
``normal_cos`` > −1 also cuts Ω's edges between points whose normals' cosine is below it (a sunlit
floor does not fill the wall it meets).  On the shipped sample, end to end with the registered photo
(``bench/photos/end_to_end.py``): photo_sun view1 0.52 → 1.06 ×, view2 0.86 → 0.95 × the path tracer.

A component of Ω with **no** edge to ∂Ω has no boundary condition (the matrix is singular there,
solutions L + constant): it **keeps its LDR colour** (the constant 0 — the solution whose mean equals
the LDR mean), stays ``valid = 0`` and is counted and logged.

``mode``: ``lum`` solves one system on the luminance Y (CIE Y of linear RGB) and sets
H = L · Y_H / Y_L (LDR chromaticity kept; grey when Y_L = 0); ``rgb`` solves one system per channel
(one factorisation, three right-hand sides).

Huge dynamic range — ``space``: ``linear`` (default, Eq. 2 as published) can go negative where the
LDR guidance falls faster than the boundary values allow (H − L is bounded by the extreme boundary
values of H − L, not by 0); such values are **clamped to 0** and counted in the report
(``negative_clamped``).  ``log`` solves the same equation on log(max(·, floor)) of both H and L
(floor = ``log_floor``): the guidance becomes a ratio and the result exp(…) is positive by
construction — better suited when boundary values span decades.  Non-finite results cannot arise
from finite inputs with a non-singular system; they are checked anyway and fall back to the LDR
colour (counted).

Solvers (never dense): ``direct`` — scipy SuperLU of the sparse matrix; ``amg`` — pyamg smoothed
aggregation as the preconditioner of CG (relative residual ``tol``); ``auto`` — direct up to
``direct_max`` unknowns, amg above.  The output marks solved points ``valid = 1``, ``source = 2``.
No invalid point → the input is copied unchanged (log line + ``skipped`` in the report).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

from ..config import StageConfig
from ..errors import InputError
from ..runtime import Timings, get_logger, held_stops

log = get_logger("poisson")


@dataclass
class PoissonConfig(StageConfig):
    k: int = field(default=16, metadata={"help": "neighbours of the kNN graph (symmetrised by union)"})
    mode: str = field(default="rgb", metadata={
        "help": "lum: one system on luminance, LDR chromaticity kept; rgb: one system per channel",
        "choices": ("lum", "rgb")})
    space: str = field(default="linear", metadata={
        "help": "linear: Eq. 2 as published, negatives clamped to 0 and counted; log: Eq. 2 on log values (always positive)",
        "choices": ("linear", "log")})
    solver: str = field(default="auto", metadata={
        "help": "direct (SuperLU), amg (pyamg-preconditioned CG) or auto (direct up to direct_max unknowns)",
        "choices": ("auto", "direct", "amg")})
    direct_max: int = field(default=20_000, metadata={
        "help": "auto solver: most unknowns for the direct solver (bench: SuperLU 15.7 s vs AMG-CG 9.3 s at 50k)"})
    tol: float = field(default=1e-10, metadata={"help": "amg/CG relative residual tolerance"})
    log_floor: float = field(default=1e-6, metadata={"help": "space=log: values are floored here before the log [LDR units]"})
    rim: str = field(default="free", metadata={
        "help": "dirichlet: every known neighbour bounds Ω (Eq. 2 as published: Ω's excess over LDR falls to 0 at "
                "the unsaturated rim); free: Ω's edges to kept-LDR points (source 0) are cut, so an overexposed "
                "region is filled flat from its projected points and one with none keeps LDR",
        "choices": ("dirichlet", "free")})
    normal_cos: float = field(default=-1.0, metadata={
        "help": "cut Ω's edges between points whose normals' cosine is below this (−1: keep all; 0.5: surfaces "
                "meeting at more than 60° do not fill each other)"})

    def check(self) -> None:
        self._require(self.k >= 1, "k", "must be ≥ 1")
        self._require(self.mode in ("lum", "rgb"), "mode", "must be lum or rgb")
        self._require(self.space in ("linear", "log"), "space", "must be linear or log")
        self._require(self.solver in ("auto", "direct", "amg"), "solver", "must be auto, direct or amg")
        self._require(self.direct_max >= 0, "direct_max", "must be ≥ 0")
        self._require(0 < self.tol < 1, "tol", "must be in (0, 1)")
        self._require(self.log_floor > 0, "log_floor", "must be > 0")
        self._require(self.rim in ("dirichlet", "free"), "rim", "must be dirichlet or free")
        self._require(-1.0 <= self.normal_cos <= 1.0, "normal_cos", "must be in [−1, 1]")


# ----------------------------------------------------------------------------- pure functions
def knn_graph(points: np.ndarray, k: int, touching: np.ndarray | None = None, chunk: int = 250_000) -> sp.csr_matrix:
    """Symmetric (union) kNN adjacency, (N,N) CSR of 1.0, no self loops.

    ``touching`` (bool (N,)): keep only the edges with at least one end in it — for Ω this is all
    that Eq. 2 reads (every N_p, p ∈ Ω, is complete), at a fraction of the memory. Queried in chunks.
    """
    from scipy.spatial import cKDTree

    n = len(points)
    k = min(k, n - 1)
    if k <= 0:
        return sp.csr_matrix((n, n))
    tree = cKDTree(points)
    rs, cs = [], []
    for a0 in range(0, n, chunk):
        with held_stops():   # SciPy's worker threads use these arrays
            _, idx = tree.query(points[a0:a0 + chunk], k=k + 1, workers=-1)
        m = len(idx)
        idx = idx.reshape(m, k + 1)
        rows = np.repeat(np.arange(a0, a0 + m), k + 1).reshape(m, k + 1)
        notself = idx != rows
        # keep the first k non-self neighbours per row (the point itself may not come first among duplicates)
        keep = notself & (np.cumsum(notself, axis=1) <= k)
        if touching is not None:
            keep &= touching[rows] | touching[idx]
        rs.append(rows[keep])
        cs.append(idx[keep])
    r = np.concatenate(rs)
    a = sp.csr_matrix((np.ones(len(r)), (r, np.concatenate(cs))), shape=(n, n))
    a = a.maximum(a.T).tocsr()
    a.setdiag(0)
    a.eliminate_zeros()
    a.data[:] = 1.0
    return a


def cut_edges(graph: sp.csr_matrix, omega: np.ndarray, normals: np.ndarray | None = None, normal_cos: float = -1.0,
              rim: np.ndarray | None = None) -> tuple[sp.csr_matrix, int]:
    """``graph`` without the edges that touch Ω and either join points whose normals' cosine is below
    ``normal_cos`` (with ``normals``) or reach a point of ``rim`` (bool (N,)); returns (graph, edges cut)."""
    g = sp.triu(graph, k=1).tocoo()
    touch = omega[g.row] | omega[g.col]
    cut = np.zeros(len(g.row), dtype=bool)
    if normals is not None and normal_cos > -1.0:
        nrm = np.asarray(normals, dtype=np.float64)
        cut |= touch & (np.einsum("ij,ij->i", nrm[g.row], nrm[g.col]) < normal_cos)
    if rim is not None:
        cut |= (omega[g.row] & rim[g.col]) | (omega[g.col] & rim[g.row])
    keep = ~cut
    a = sp.csr_matrix((np.ones(int(keep.sum())), (g.row[keep], g.col[keep])), shape=graph.shape)
    return (a + a.T).tocsr(), int(cut.sum())


def solve_poisson(graph: sp.csr_matrix, omega: np.ndarray, known: np.ndarray, guide: np.ndarray,
                  solver: str = "auto", tol: float = 1e-10, direct_max: int = 20_000
                  ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Eq. 2 on ``graph`` for the points ``omega`` (bool (N,)).

    known: (N,) or (N,C) HDR values (used where ~omega); guide: same shape, the LDR values L.
    Returns (H, free, info): H = known outside Ω, the solution on Ω, and L on Ω components without
    boundary (``free`` (N,) bool marks those points); info has the counts (components, no-boundary components/points, solver, residual).
    """
    from scipy.sparse.csgraph import connected_components

    one = known.ndim == 1
    known = known.reshape(len(known), -1).astype(np.float64)
    guide = guide.reshape(len(guide), -1).astype(np.float64)
    out = known.copy()
    oidx = np.nonzero(omega)[0]
    info: dict[str, Any] = {"unknowns": int(len(oidx))}
    free_n = np.zeros(len(known), dtype=bool)
    if len(oidx) == 0:
        return (out[:, 0] if one else out), free_n, info
    g = graph.tocsr()
    deg = np.asarray(g.sum(axis=1)).ravel()
    w_oo = g[oidx][:, oidx].tocsr()
    bmask = ~omega
    w_ob = g[oidx][:, np.nonzero(bmask)[0]].tocsr()
    ncomp, lab = connected_components(w_oo, directed=False)
    has_b = np.zeros(ncomp, dtype=bool)
    touches = np.asarray(w_ob.sum(axis=1)).ravel() > 0
    has_b[lab[touches]] = True
    free = ~has_b[lab]  # Ω points of components without boundary
    info.update({"components": int(ncomp), "components_without_boundary": int((~has_b).sum()),
                 "points_without_boundary": int(free.sum())})
    out[oidx[free]] = guide[oidx[free]]
    free_n[oidx[free]] = True
    sel = ~free
    if not sel.any():
        return (out[:, 0] if one else out), free_n, info
    s_idx = oidx[sel]
    a = (sp.diags(deg[s_idx]) - w_oo[sel][:, sel]).tocsr()
    # right-hand side: boundary values + Σ_q v_pq = deg·L(p) − Σ_q L(q)
    b = np.asarray(w_ob[sel] @ known[bmask]) + deg[s_idx, None] * guide[s_idx] - np.asarray(g[s_idx] @ guide)
    if solver == "auto":
        solver = "direct" if len(s_idx) <= direct_max else "amg"
    info["solver"] = solver
    x = np.empty_like(b)
    if solver == "direct":
        from scipy.sparse.linalg import splu

        lu = splu(a.tocsc())
        for ch in range(b.shape[1]):
            x[:, ch] = lu.solve(b[:, ch])
    else:
        import pyamg

        ml = pyamg.smoothed_aggregation_solver(a, symmetry="symmetric")
        iters = []
        for ch in range(b.shape[1]):
            res: list[float] = []
            x[:, ch] = ml.solve(b[:, ch], tol=tol, accel="cg", maxiter=1000, residuals=res)
            iters.append(len(res))
        info["iterations"] = iters
    r = np.asarray(a @ x) - b
    info["relative_residual"] = float(np.linalg.norm(r) / max(np.linalg.norm(b), 1e-300))
    out[s_idx] = x
    return (out[:, 0] if one else out), free_n, info


def fill_colors(points: np.ndarray, colors: np.ndarray, ldr: np.ndarray, omega: np.ndarray, cfg: PoissonConfig,
                graph: sp.csr_matrix | None = None) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Colours for Ω by Eq. 2: (colours (N,3) float64, solved (N,) bool, info)."""
    from ..io import luminance

    if graph is None:
        graph = knn_graph(points, cfg.k)
    hdr = colors.astype(np.float64)
    ldr = ldr.astype(np.float64)
    if cfg.mode == "lum":
        known = luminance(hdr).astype(np.float64)
        guide = luminance(ldr).astype(np.float64)
    else:
        known, guide = hdr, ldr
    if cfg.space == "log":
        known = np.log(np.maximum(known, cfg.log_floor))
        guide = np.log(np.maximum(guide, cfg.log_floor))
    sol, free, info = solve_poisson(graph, omega, known, guide, cfg.solver, cfg.tol, cfg.direct_max)
    sol = sol.reshape(len(sol), -1)
    if cfg.space == "log":
        sol = np.exp(sol)
    solved = omega & ~free
    vals = sol[solved]
    bad = ~np.isfinite(vals).all(axis=1)
    neg = (vals < 0).any(axis=1) & ~bad
    info["nonfinite_fallback"] = int(bad.sum())
    info["negative_clamped"] = int(neg.sum())
    vals = np.maximum(np.where(np.isfinite(vals), vals, 0.0), 0.0)
    out = hdr.copy()
    out[free] = ldr[free]
    if cfg.mode == "lum":
        y_l = luminance(ldr[solved]).astype(np.float64)
        safe = y_l > 0
        ratio = np.where(safe, vals[:, 0] / np.where(safe, y_l, 1.0), 0.0)
        col = ldr[solved] * ratio[:, None]
        col[~safe] = vals[~safe, 0][:, None]
    else:
        col = vals
    sidx = np.nonzero(solved)[0]
    col[bad] = ldr[sidx[bad]]
    out[sidx] = col
    solved_ok = solved.copy()
    solved_ok[sidx[bad]] = False
    return out, solved_ok, info


# ----------------------------------------------------------------------------- action
def run_poisson(cloud_in: str | Path, cloud_out: str | Path, cfg: PoissonConfig, preview: str | Path | None = None,
                ldr: str | Path | None = None) -> dict[str, Any]:
    """Read the reprojected cloud (and optionally the LDR cloud for the guidance L), fill Ω by Eq. 2,
    write the cloud (solved points valid = 1, source = 2) and ``<out stem>.json``.

    L: the colours of ``ldr`` when given (must have the same points); otherwise the input colours,
    clipped to [0,1] on projected points (source = 1, whose LDR colour reproject replaced) — exact
    for kept and invalid points, which still hold their LDR colour."""
    from .. import io

    t = Timings()
    t0 = time.perf_counter()
    cloud_out = Path(cloud_out)
    with t.step("read"):
        c = io.read_cloud(cloud_in)
    n = len(c)
    valid = c.valid if c.valid is not None else np.ones(n, dtype=np.uint8)
    omega = valid == 0
    n_omega = int(omega.sum())
    report: dict[str, Any] = {"input": str(cloud_in), "points": n, "invalid": n_omega, "config": cfg.as_dict()}
    if c.valid is None:
        log.info("%s has no 'valid' property: every point counts as valid", cloud_in)
    if n_omega == 0:
        log.info("no invalid point: the cloud is copied unchanged")
        report.update({"skipped": "no invalid point", "solved": 0})
        with t.step("write"):
            io.write_cloud(cloud_out, c)
    else:
        report["skipped"] = None
        if ldr is not None:
            l = io.read_cloud(ldr)
            if len(l) != n or not np.array_equal(l.points, c.points):
                raise InputError(ldr, f"is not the same point set as {cloud_in} ({len(l)} vs {n} points)")
            guide = l.colors.astype(np.float64)
            report["guidance"] = f"LDR colours of {ldr}"
        else:
            guide = c.colors.astype(np.float64).copy()
            if c.source is not None:
                proj = c.source == 1
                guide[proj] = np.clip(guide[proj], 0.0, 1.0)
            report["guidance"] = "input colours, clipped to [0,1] on projected points"
        log.info("%d invalid points to fill (k=%d, %s, %s space)", n_omega, cfg.k, cfg.mode, cfg.space)
        with t.step("graph"):
            g = knn_graph(c.points.astype(np.float64), cfg.k, touching=omega)
            rim = None
            if cfg.rim == "free":
                if c.source is None:
                    log.warning("--rim free needs the cloud's 'source' property (reproject's output): Eq. 2's rim kept")
                else:
                    rim = (valid == 1) & (c.source == 0)
            if rim is not None or cfg.normal_cos > -1.0:
                g, report["edges_cut"] = cut_edges(g, omega, c.normals, cfg.normal_cos, rim)
                log.info("cut %d of Ω's edges (rim %s, normal cosine < %.2f)", report["edges_cut"],
                         "free" if rim is not None else "dirichlet", cfg.normal_cos)
        with t.step("solve"):
            colors, solved, info = fill_colors(c.points.astype(np.float64), c.colors, guide, omega, cfg, graph=g)
        report.update(info)
        report["solved"] = int(solved.sum())
        report["graph_edges_touching_omega"] = int(g.nnz // 2)
        if info.get("components_without_boundary"):
            if "edges_cut" in report:
                log.info("%d overexposed region(s) (%d points) touch no projected point: they keep their LDR colour "
                         "(a lower bound; a photo of them would pin them)",
                         info["components_without_boundary"], info["points_without_boundary"])
            else:
                log.warning("%d component(s) of Ω (%d points) touch no valid point: they keep their LDR colour",
                            info["components_without_boundary"], info["points_without_boundary"])
        if info.get("negative_clamped"):
            log.warning("%d solved points were negative and were clamped to 0 (try --space log)", info["negative_clamped"])
        if info.get("nonfinite_fallback"):
            log.warning("%d solved points were not finite and keep their LDR colour", info["nonfinite_fallback"])
        log.info("solved %d points (%d components, solver %s, relative residual %.2e)", report["solved"],
                 info["components"], info.get("solver"), info.get("relative_residual", 0.0))
        valid_o = valid.copy()
        valid_o[solved] = 1
        source = c.source.copy() if c.source is not None else np.zeros(n, dtype=np.uint8)
        source[solved] = 2
        quality = c.quality.copy() if c.quality is not None else np.zeros(n, dtype=np.float32)
        quality[solved] = 0.0
        out = io.Cloud(c.points, c.normals, colors.astype(np.float32), valid=valid_o, quality=quality, source=source)
        with t.step("write"):
            io.write_cloud(cloud_out, out)
        c = out
    if preview is not None:
        from .splats import preview_cloud

        preview_cloud(preview, c)
    report.update({"output": str(cloud_out), "timings": t.as_dict(), "seconds": time.perf_counter() - t0})
    io.write_json(cloud_out.with_suffix(".json"), report)
    log.info("wrote %s in %.2f s", cloud_out, time.perf_counter() - t0)
    return report
