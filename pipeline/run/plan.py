"""The planner: what a run of the pipeline needs, decided from its inputs, each decision with the number
that decided it (issue 27, "model only what the scene requires").

A :class:`Decision` has a name, whether the work is needed, the value that decided it, the threshold it was
compared with, the rule in words, the stages it affects and when it is made. The core is pure functions on
arrays and options (:func:`decide_expansion`, :func:`decide_poisson`, :func:`decide_glossy`,
:func:`record_emitters`); :func:`make_plan` reads the files they need and :class:`Plan` is what
``pcrelight run`` follows, prints (``--explain``) and writes into ``run.json``.

The decisions:

- **expansion** — the LDR cloud's overexposed points (CIE Y of the decoded linear colours > reproject's
  ``t_l``, :func:`pipeline.color.overexposed_mask`, the rule reproject uses to choose the points it gives HDR
  values). None → expose-match, render-cubemaps, patchmatch, reproject and poisson are skipped and build-bsh
  reads ``cloud_ldr.ply`` as the HDR cloud. This is what the full chain gives on such a cloud: reproject
  passes every point through with its decoded LDR colour (valid, source 0; float32 → float64 → float32,
  exact), poisson finds no invalid point and copies it, and build-bsh reads only positions, normals and
  colours — so bsh.npz and relit.exr are the same bytes (tests/test_plan.py). Only reproject's ``t_l``
  decides: render-cubemaps' and patchmatch's ``t_l`` only choose where cube maps look and which pixels are
  matched; with no point over reproject's, nothing they produce reaches a point.
- **faces** — render-cubemaps and patchmatch, decided after expose-match from ``exposure.npz``: with a registered
  photo (a camera in exposure.npz), reproject's ``photo_direct`` and ``--unseen poisson|ldr``, every overexposed
  point the photo sees takes α × the photo and every other gets no face sample (invalid with its LDR colour, or
  its LDR value), so the faces reach no byte of cloud_proj.ply or cloud_hdr.ply
  (:func:`pipeline.expansion.reproject.photo_alone`): both are skipped and reproject runs on the photo alone
  (tests/test_plan.py: the same bytes as ``--no-plan``'s). Needs patchmatch's ``pmatch``, reproject's ``method``
  auto and render-cubemaps' default splat radii (the direct transfer's visibility uses them).
- **poisson** — decided after reproject: the points ``cloud_proj.ply`` marks invalid (``valid`` = 0). None →
  poisson is skipped (it would copy the cloud unchanged) and build-bsh reads ``cloud_proj.ply``.
- **glossy** — relight's rule, :func:`pipeline.relight.inputs.choose_brdf` (decided here and handed to relight as
  its ``brdf``, so relight does not decide again): Lambert unless a PBR material has metallic > 0,
  roughness < 1 or a metallic-roughness texture (after relight's ``metallic``/``roughness`` overrides). A
  Lambert object gets no glossy work (no BRDF evaluation, no lobe micro-buffer).
- **microbuffer** — a Lambert object (the glossy decision: no glossy work) gets the coarsest micro-buffer side m
  whose measured Lambert error is within the preset's bound of the configured m's on every measured scene and
  view (:func:`decide_microbuffer`; the table :data:`RELIGHT_TABLE`, written by ``bench/plan/bench_plan.py --table``:
  the noise-corrected 4×4-block RMS against the path-traced ``full_<view>_lambert.exr`` per m, on the shipped
  scene and the lamp room). The bound: ``exact`` and no preset 1.0 (no worse than the configured m), ``balanced``
  1.15, ``fast`` 2.0 — the trade's factors (:mod:`pipeline.measure.trade`). Kept when ``microbuffer`` is given in the
  run's ``[relight]`` table or the object is glossy.
- **cut** — the hybrid gatherer's shared cut: its hand-off threshold Ω_tr (``omega_tr`` × Ω_pix, the solid angle
  below which a node's sub-tree goes to each receiver's own walk) from the object's footprint on the image
  (projected bounding box [pixels]) and its distance to the nearest cloud point (over its bounding radius), both
  from :func:`object_geometry`: the Ω_tr whose relight CPU time (÷ the configured Ω_tr's) was the least on
  average over the measured scene/view/size cases nearest to this one in (log₂ footprint, log₂ gap ratio), when
  at least :data:`CUT_MIN_SAVING` less (:func:`decide_cut`, the same table). The hybrid's cut
  gives every receiver the classic walk's cut whatever Ω_tr is (pipeline/gather/cut.py), so the decision
  changes the time, not the image. Kept when ``omega_tr`` is given or the method is not hybrid.
- **emitters** — build-bsh's decision (it needs the tree's leaves: isolated leaves and the leaves of small
  objects brighter than ``closed_contrast`` × the median luminance), recorded from its report ``bsh.json``
  after it ran; relight's final gather adds them.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..color import luminance
from ..config import BALANCED_FACTOR, FAST_FACTOR, PRESET_DIR
from ..runtime import get_logger

log = get_logger("plan")

EXPANSION = ("expose-match", "render-cubemaps", "patchmatch", "reproject", "poisson")
FACES = ("render-cubemaps", "patchmatch")
HDR_CLOUDS = ("cloud_ldr", "cloud_proj", "cloud_hdr")   # what build-bsh may read (workspace names)
# The measured table the relight decisions read (bench/plan/bench_plan.py --table writes it; one row per scene, view,
# image size, knob and value): columns TABLE_FIELDS.
RELIGHT_TABLE = PRESET_DIR / "relight_plan.csv"
TABLE_FIELDS = ("scene", "view", "size", "footprint_px", "gap_ratio", "knob", "value", "err", "mean_ratio",
                "relight_s", "relight_cpu_s", "load1", "nodes_per_pixel", "relit_md5")
# The error bound of each preset for the micro-buffer decision: a multiple of the configured m's error.
PRESET_BOUNDS = {"": 1.0, "exact": 1.0, "balanced": BALANCED_FACTOR, "fast": FAST_FACTOR}
# The cut decision changes Ω_tr only when the measured relight CPU time falls by at least this share (the CPU
# seconds of one relight vary by ~5–10 % on the shared machine the table was measured on).
CUT_MIN_SAVING = 0.10
CUT_NEAR_LOG2 = 0.5        # measured cases this close (log₂ units) to the nearest one count with it


@dataclass(frozen=True)
class Decision:
    """One decision of the planner. ``needed``: whether the work is done (None: not decided yet, made when an
    earlier stage has run); ``value``: the number (or counts) that decided it; ``threshold``: what it was
    compared with; ``rule``: the comparison in words; ``stages``: the stages it affects; ``why``: one
    sentence with the numbers; ``when``: ``plan`` (from the inputs), ``after reproject``, ``build-bsh``."""

    name: str
    needed: bool | None
    value: Any
    threshold: Any
    rule: str
    stages: tuple[str, ...]
    why: str
    when: str = "plan"

    def as_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["stages"] = list(self.stages)
        return d


# ----------------------------------------------------------------------------- the decisions (pure)
def decide_expansion(colors: np.ndarray, t_l: float) -> Decision:
    """Expansion needed iff some point's LDR luminance (CIE Y of linear RGB, float32 — reproject's
    :func:`pipeline.color.overexposed_mask`) exceeds ``t_l``. ``colors``: (N, 3) linear, as read."""
    y = luminance(colors) if len(colors) else np.zeros(0, np.float32)
    n_over = int((y > t_l).sum())
    y_max = float(y.max()) if len(y) else 0.0
    value = {"overexposed": n_over, "points": int(len(y)), "max_luminance": round(y_max, 6)}
    if n_over:
        why = (f"{n_over} of {len(y)} points overexposed (LDR luminance > t_l {t_l:g}; "
               f"{100.0 * n_over / len(y):.2f} %, brightest {y_max:.4g})")
    else:
        why = (f"no overexposed point: 0 of {len(y)} points with LDR luminance > t_l {t_l:g} "
               f"(brightest {y_max:.4g}); build-bsh reads cloud_ldr.ply decoded to linear")
    return Decision("expansion", n_over > 0, value, t_l, "points with LDR luminance (CIE Y, linear) > t_l (reproject's)",
                    EXPANSION, why)


def faces_rules(cfgs: Mapping[str, Any]) -> list[str]:
    """The options that make the faces needed whatever expose-match finds (empty: exposure.npz decides)."""
    from ..expansion.splats import SPLAT_K, SPLAT_SCALE

    why: list[str] = []
    pm, rp, rc = cfgs.get("patchmatch"), cfgs.get("reproject"), cfgs.get("render-cubemaps")
    if pm is not None and pm.method != "pmatch":
        why.append(f"patchmatch --method {pm.method} (not pmatch: no registered-photo transfer)")
    if rp is not None:
        if rp.method != "auto":
            why.append(f"reproject --method {rp.method}")
        if not rp.photo_direct:
            why.append("reproject --no-photo-direct")
        if rp.unseen in ("lookalike", "calibrated"):
            why.append(f"reproject --unseen {rp.unseen} (the unseen points take the faces' look-alike samples)")
    if rc is not None and (rc.splat_k != SPLAT_K or rc.splat_scale != SPLAT_SCALE):
        why.append(f"render-cubemaps' splat radii (k {rc.splat_k}, scale {rc.splat_scale:g}) are not the defaults the "
                   "direct transfer's visibility uses without cameras.npz")
    return why


def decide_faces(rules: list[str], registered: bool | None, unseen: str = "poisson") -> Decision:
    """Cube-map faces (render-cubemaps, patchmatch) needed unless the registered photo alone decides every
    overexposed point: no option in ``rules`` (:func:`faces_rules`) and ``registered`` (exposure.npz holds the
    photo's camera; None: not known yet)."""
    rule = "needed unless exposure.npz holds the registered camera and reproject's --unseen is poisson or ldr"
    if rules:
        return Decision("faces", True, {"rules": rules}, None, rule, FACES, "cube-map faces needed: " + "; ".join(rules))
    if registered is None:
        return pending("faces", FACES, "run unless expose-match registers the photo (decided from exposure.npz when "
                                       "expose-match has run)", "after expose-match")
    if registered:
        why = (f"no cube maps, no PatchMatch: the photo is registered (exposure.npz holds its camera, or a set's kept "
               f"photos theirs) and --unseen {unseen}: the points it sees take α × the photo, the others no face "
               "sample, so the faces would change no byte of the cloud")
    else:
        why = "cube-map faces needed: the photo is not registered (exposure.npz holds no camera; expose-match --photo-fov)"
    return Decision("faces", not registered, {"registered": registered, "unseen": unseen}, None, rule, FACES, why,
                    "after expose-match")


def decide_poisson(valid: np.ndarray | None) -> Decision:
    """Poisson needed iff some point of reproject's cloud is invalid (``valid`` = 0; no ``valid`` property:
    every point counts as valid, as poisson reads it)."""
    n = 0 if valid is None else int(len(valid))
    bad = 0 if valid is None else int((np.asarray(valid) == 0).sum())
    if bad:
        why = f"{bad} of {n} points invalid after reproject ({100.0 * bad / max(n, 1):.2f} %): Eq. 2 fills them"
    else:
        why = f"no invalid point after reproject (0 of {n}): build-bsh reads cloud_proj.ply"
    return Decision("poisson", bad > 0, {"invalid": bad, "points": n}, 0, "points with valid = 0 in cloud_proj.ply > 0",
                    ("poisson",), why, "after reproject")


def decide_glossy(parts: list[dict], relight_cfg: Any) -> Decision:
    """Relight's BRDF rule (:func:`pipeline.relight.inputs.choose_brdf`) with the numbers behind it: the largest
    metallic and smallest roughness over the object's PBR materials (after relight's overrides), and how
    many have a metallic-roughness texture."""
    from ..relight.inputs import choose_brdf

    kind, reason = choose_brdf(relight_cfg, parts)
    pbr = [p for p in parts if p.get("pbr")]
    met = [relight_cfg.metallic if relight_cfg.metallic is not None else float(p["metallic"]) for p in pbr]
    rough = [relight_cfg.roughness if relight_cfg.roughness is not None else float(p["roughness"]) for p in pbr]
    value = {"brdf": kind, "pbr_materials": len(pbr), "parts": len(parts),
             "metallic_max": round(max(met), 6) if met else None, "roughness_min": round(min(rough), 6) if rough else None,
             "mr_textures": sum(p.get("mr_tex") is not None for p in pbr)}
    nums = (f"metallic max {value['metallic_max']:g}, roughness min {value['roughness_min']:g}, "
            f"{value['mr_textures']} metallic-roughness texture(s) over {len(pbr)} PBR material(s)" if pbr
            else f"no PBR material in {len(parts)} part(s)")
    if relight_cfg.brdf:
        why = f"BRDF {kind}: given (--brdf)"
    elif kind == "lambert":
        why = f"BRDF lambert: no glossy work ({nums}; glossy if metallic > 0 or roughness < 1 or a texture)"
    else:
        why = f"BRDF {kind}: glossy work ({nums}; {reason})"
    return Decision("glossy", kind != "lambert", value, {"metallic": 0.0, "roughness": 1.0},
                    "a PBR material with metallic > 0, roughness < 1 or a metallic-roughness texture (relight.choose_brdf)",
                    ("relight",), why)


def record_emitters(bsh_report: Mapping[str, Any]) -> Decision:
    """build-bsh's emitter decision as its report (``bsh.json``) records it."""
    cfg, st = bsh_report.get("config", {}), bsh_report.get("counts", {})
    n, cand, comp = int(st.get("n_emitters", 0)), int(st.get("n_emitter_candidates", 0)), int(st.get("n_compact", 0))
    mode = cfg.get("emitters", "?")
    why = (f"{n} emitters (--emitters {mode}; {cand} candidate leaves: the isolated ones and {comp} of small objects "
           f"brighter than {cfg.get('closed_contrast', '?')} × the median luminance within {cfg.get('emitter_size', '?')} "
           "splat radii)" + ("" if n else ": relight adds no emitter"))
    return Decision("emitters", n > 0, {"emitters": n, "candidates": cand, "compact_leaves": comp},
                    {"closed_contrast": cfg.get("closed_contrast"), "emitter_size": cfg.get("emitter_size")},
                    "isolated leaves and small bright objects (build-bsh --emitters)", ("build-bsh", "relight"), why,
                    "build-bsh")


def read_table(path: str | Path | None = None) -> list[dict[str, str]]:
    """The measured relight table (:data:`RELIGHT_TABLE` by default); [] when the file is absent."""
    import csv

    f = Path(path) if path is not None else RELIGHT_TABLE
    if not f.exists():
        return []
    with open(f, newline="") as fh:
        return list(csv.DictReader(fh))


def object_geometry(obj_points: np.ndarray, cloud_points: np.ndarray, cam: Any) -> dict[str, float]:
    """The object as the relight decisions see it: ``footprint_px`` the area of its vertices' projected bounding
    box clipped to the viewport [pixels] (``cam``: :class:`pipeline.camera.Camera`), ``radius_m`` its bounding
    radius (half the box diagonal) [m], ``gap_m`` the smallest distance from a vertex to a cloud point [m],
    ``gap_ratio`` = gap / radius, ``distance_m`` from the eye to the box centre [m]."""
    from scipy.spatial import cKDTree

    p = np.asarray(obj_points, np.float64).reshape(-1, 3)
    lo, hi = p.min(0), p.max(0)
    radius = float(np.linalg.norm(hi - lo) / 2)
    r, u, f = cam.basis()
    d = p - np.asarray(cam.eye, np.float64)
    z = d @ f
    front = z > 1e-9
    W, H = cam.size
    t = math.tan(math.radians(cam.fov_deg) / 2)
    if front.any():
        x = (d[front] @ r) / z[front] / (t * W / H)
        y = (d[front] @ u) / z[front] / t
        px = np.clip((x + 1) / 2 * W, 0, W)
        py = np.clip((1 - y) / 2 * H, 0, H)
        foot = float((px.max() - px.min()) * (py.max() - py.min()))
    else:
        foot = 0.0
    gap = float(cKDTree(np.asarray(cloud_points, np.float64)).query(p, k=1)[0].min()) if len(cloud_points) else math.inf
    return {"footprint_px": round(foot, 3), "radius_m": round(radius, 6), "gap_m": round(gap, 6),
            "gap_ratio": round(gap / radius, 6) if radius > 0 else math.inf,
            "distance_m": round(float(np.linalg.norm((lo + hi) / 2 - np.asarray(cam.eye, np.float64))), 6)}


def decide_microbuffer(table: list[dict[str, str]], brdf: str, m_cfg: int, preset: str = "",
                       given: bool = False) -> Decision:
    """The micro-buffer side of a Lambert object: the smallest measured m < ``m_cfg`` whose Lambert error
    (``knob`` microbuffer rows of ``table``) is ≤ bound × the error at ``m_cfg`` on every (scene, view, size)
    measured at both (bound: :data:`PRESET_BOUNDS` of ``preset``); ``m_cfg`` when none is, when the object is
    glossy, when ``given`` (``microbuffer`` in the run's [relight] table) or when the table lacks ``m_cfg``."""
    bound = PRESET_BOUNDS.get(preset, 1.0)
    rule = ("a Lambert object: the smallest m whose measured Lambert error ≤ bound × the configured m's on every "
            f"measured scene/view ({RELIGHT_TABLE.name})")
    thr = {"bound": bound, "preset": preset or "none", "configured_m": m_cfg}

    def keep(why: str, **extra: Any) -> Decision:
        return Decision("microbuffer", True, {"m": m_cfg, "configured": m_cfg, **extra}, thr, rule, ("relight",), why)

    if given:
        return keep(f"m {m_cfg}: given in [relight]")
    if brdf != "lambert":
        return keep(f"m {m_cfg}: the object is glossy ({brdf}); the table measures Lambert only")
    err: dict[tuple[str, str, str], dict[int, float]] = {}
    for r in table:
        if r.get("knob") == "microbuffer" and r.get("err", "") not in ("", "nan"):
            err.setdefault((r["scene"], r["view"], r["size"]), {})[int(float(r["value"]))] = float(r["err"])
    pairs = [k for k, v in err.items() if m_cfg in v]
    if not pairs:
        return keep(f"m {m_cfg}: not in the measured table ({len(table)} rows)")
    sides = sorted({m for k in pairs for m in err[k] if m < m_cfg})
    for m in sides:                                         # the coarsest first
        if all(m in err[k] for k in pairs):
            ratios = {k: err[k][m] / err[k][m_cfg] if err[k][m_cfg] > 0 else math.inf for k in pairs}
            worst_k = max(ratios, key=lambda k: ratios[k])
            if ratios[worst_k] <= bound:
                value = {"m": m, "configured": m_cfg, "worst_ratio": round(ratios[worst_k], 4),
                         "worst": "/".join(worst_k), "measured": len(pairs)}
                why = (f"m {m} instead of {m_cfg}: a Lambert object, measured error at m {m} ≤ {bound:g} × m {m_cfg}'s on "
                       f"all {len(pairs)} measured scene/views (worst {ratios[worst_k]:.3f}× on {'/'.join(worst_k)}; "
                       f"preset {preset or 'none'})")
                return Decision("microbuffer", False, value, thr, rule, ("relight",), why)
    best = {m: max(err[k][m] / err[k][m_cfg] for k in pairs if m in err[k]) for m in sides}
    return keep(f"m {m_cfg}: no coarser m within {bound:g}× its error on every measured scene/view (worst ratios "
                + ", ".join(f"m {m} {x:.3f}×" for m, x in best.items()) + ")", worst_ratios=best)


def decide_cut(table: list[dict[str, str]], method: str, omega_cfg: float, geom: Mapping[str, float] | None,
               given: bool = False) -> Decision:
    """The hybrid cut's hand-off threshold Ω_tr [× Ω_pix] from the ``knob`` omega_tr rows of ``table``: the
    measured cases (scene, view, size) nearest to ``geom`` (:func:`object_geometry`) in (log₂ footprint, log₂ gap
    ratio) — every case within :data:`CUT_NEAR_LOG2` of the nearest distance, so that two measurements of the same
    geometry count together — and the Ω_tr whose relight CPU seconds over the configured one's, averaged over those
    cases, is the least, when that mean is at most 1 − :data:`CUT_MIN_SAVING`. ``omega_cfg`` when ``given``, when
    ``method`` is not hybrid, or without a table or geometry."""
    rule = ("hybrid: the Ω_tr with the least mean measured relight CPU time (÷ the configured Ω_tr's) over the "
            f"measured cases nearest in (log2 footprint px, log2 gap/radius), if ≥ {100 * CUT_MIN_SAVING:.0f} % less")
    thr = {"configured_omega_tr": omega_cfg, "min_saving": CUT_MIN_SAVING}
    g = dict(geom or {})

    def keep(why: str) -> Decision:
        return Decision("cut", True, {**g, "omega_tr": omega_cfg, "configured": omega_cfg}, thr, rule, ("relight",), why)

    if given:
        return keep(f"Ω_tr {omega_cfg:g}: given in [relight]")
    if method != "hybrid":
        return keep(f"--method {method}: no hybrid cut to size (Ω_tr applies to hybrid)")
    if not geom or not (geom.get("footprint_px", 0) > 0) or not math.isfinite(geom.get("gap_ratio", math.inf)):
        return keep(f"Ω_tr {omega_cfg:g}: the object's footprint or distance is unknown")
    runs: dict[tuple[str, str, str], dict[float, dict[str, str]]] = {}
    for r in table:
        if r.get("knob") == "omega_tr":
            runs.setdefault((r["scene"], r["view"], r["size"]), {})[float(r["value"])] = r
    runs = {k: v for k, v in runs.items() if omega_cfg in v}
    if not runs:
        return keep(f"Ω_tr {omega_cfg:g}: not in the measured rows ({RELIGHT_TABLE.name})")

    def dist(k: tuple[str, str, str]) -> float:
        r0 = next(iter(runs[k].values()))
        return math.hypot(math.log2(max(float(r0["footprint_px"]), 1e-9) / geom["footprint_px"]),
                          math.log2(max(float(r0["gap_ratio"]), 1e-9) / max(geom["gap_ratio"], 1e-9)))

    d0 = min(dist(k) for k in runs)
    near = sorted(k for k in runs if dist(k) <= d0 + CUT_NEAR_LOG2)
    omegas = sorted(set.intersection(*(set(runs[k]) for k in near)))
    ratio = {w: float(np.mean([float(runs[k][w]["relight_cpu_s"]) / float(runs[k][omega_cfg]["relight_cpu_s"])
                               for k in near])) for w in omegas}
    w = min(omegas, key=lambda x: (ratio[x], x != omega_cfg))
    r0 = next(iter(runs[near[0]].values()))
    g.update(omega_tr=w if ratio[w] <= 1 - CUT_MIN_SAVING else omega_cfg, configured=omega_cfg,
             nearest=["/".join(k) for k in near], nearest_footprint_px=float(r0["footprint_px"]),
             nearest_gap_ratio=float(r0["gap_ratio"]), cpu_ratio={f"{k:g}": round(v, 4) for k, v in ratio.items()})
    nums = (f"footprint {geom['footprint_px']:.0f} px, nearest cloud point {geom['gap_m']:.3g} m = "
            f"{geom['gap_ratio']:.3g} × its radius; measured at {', '.join(g['nearest'])} "
            f"({float(r0['footprint_px']):.0f} px, {float(r0['gap_ratio']):.3g}): relight CPU ÷ Ω_tr {omega_cfg:g}'s "
            + ", ".join(f"Ω_tr {k:g} {v:.2f}" for k, v in ratio.items()))
    if g["omega_tr"] == omega_cfg:
        return Decision("cut", True, g, thr, rule, ("relight",),
                        f"Ω_tr {omega_cfg:g} kept: none measured ≥ {100 * CUT_MIN_SAVING:.0f} % faster ({nums})")
    why = f"Ω_tr {w:g} instead of {omega_cfg:g} ({nums}; the cut, so the image, is the classic walk's either way)"
    return Decision("cut", False, g, thr, rule, ("relight",), why)


def pending(name: str, stages: tuple[str, ...], why: str, when: str) -> Decision:
    """A decision that an earlier stage's output makes (not made yet)."""
    return Decision(name, None, None, None, "", stages, why, when)


# ----------------------------------------------------------------------------- the plan
@dataclass
class Plan:
    """The decisions of one run and what each stage does because of them. ``follow`` False (``[run] plan =
    false``): the decisions are still made and recorded, every stage runs as before the planner."""

    decisions: dict[str, Decision] = field(default_factory=dict)
    follow: bool = True
    unseen: str = "poisson"          # reproject's --unseen (the faces decision names it)

    def get(self, name: str) -> Decision | None:
        return self.decisions.get(name)

    def set(self, d: Decision) -> Decision:
        self.decisions[d.name] = d
        if d.needed is not None and d.name in ("microbuffer", "cut"):
            log.info("plan: %s %s — %s", d.name, "as configured" if d.needed else "decided", d.why)
        elif d.needed is not None:
            log.info("plan: %s %s — %s", d.name, "needed" if d.needed else "not needed", d.why)
        return d

    def skip_reason(self, verb: str) -> str | None:
        """Why the plan skips ``verb``, or None when it runs."""
        if not self.follow:
            return None
        ex, po, fa = self.get("expansion"), self.get("poisson"), self.get("faces")
        if verb in EXPANSION and ex is not None and ex.needed is False:
            return ex.why
        if verb in FACES and fa is not None and fa.needed is False:
            return fa.why
        if verb == "poisson" and po is not None and po.needed is False:
            return po.why
        return None

    def hdr_cloud(self) -> str:
        """The workspace name of the cloud build-bsh reads (one of :data:`HDR_CLOUDS`)."""
        if self.skip_reason("reproject"):
            return "cloud_ldr"
        if self.skip_reason("poisson"):
            return "cloud_proj"
        return "cloud_hdr"

    def overrides(self, verb: str, cfg: Any) -> dict[str, Any]:
        """Options a stage takes from the plan instead of deciding again (relight: its BRDF, micro-buffer side
        and Ω_tr)."""
        out: dict[str, Any] = {}
        if not self.follow or verb != "relight":
            return out
        g, mb, cut = self.get("glossy"), self.get("microbuffer"), self.get("cut")
        if g is not None and g.value and not cfg.brdf:
            out["brdf"] = g.value["brdf"]
        if mb is not None and mb.needed is False and mb.value["m"] != cfg.microbuffer:
            out["microbuffer"] = int(mb.value["m"])
        if cut is not None and cut.needed is False and cut.value["omega_tr"] != cfg.omega_tr:
            out["omega_tr"] = float(cut.value["omega_tr"])
        return out

    def stage_line(self, verb: str, cloud_name: str | None = None, kept: bool = False) -> str:
        """One line: ``<verb>  run|skipped|kept: <why, with the numbers>`` (``kept``: the stage's outputs are up
        to date, so the run keeps them)."""
        skip = self.skip_reason(verb)
        if skip:
            return f"{verb:<16} skipped: {skip}"
        po, fa = self.get("poisson"), self.get("faces")
        if verb == "poisson" and po is not None and po.needed is None and self.follow:
            return f"{verb:<16} run if reproject leaves a point invalid (decided from cloud_proj.ply when reproject has run)"
        if verb in FACES and fa is not None and fa.needed is None and self.follow:
            return f"{verb:<16} {fa.why}"
        notes: list[str] = []
        ex, gl, em = (self.get(n) for n in ("expansion", "glossy", "emitters"))
        if verb == "poisson" and po is not None and po.needed is not None:
            notes.append(po.why)
        elif verb in EXPANSION and ex is not None:
            notes.append(ex.why)
        if verb in FACES and fa is not None and fa.needed:
            notes.append(fa.why)
        if verb == "reproject" and self.skip_reason("render-cubemaps"):
            notes.append("the registered photo alone (no faces)")
        if verb == "build-bsh":
            notes.append(f"reads {cloud_name or self.hdr_cloud()}")  # the path build-bsh reads
            if em is not None:
                notes.append(em.why)
        if verb == "relight":
            if gl is not None:
                notes.append(gl.why)
            for d in (self.get("microbuffer"), self.get("cut")):
                if d is not None:
                    notes.append(d.why)
            if em is not None and em.needed is not None:
                notes.append(f"{em.value['emitters']} emitters from build-bsh")
        head = "kept (outputs up to date; --force reruns)" if kept else "run"
        head += "" if self.follow else " (plan = false: every stage runs)"
        return f"{verb:<16} {head}" + (": " + "; ".join(notes) if notes else "")

    def as_dict(self) -> dict[str, Any]:
        return {"follow": self.follow, "hdr_cloud": self.hdr_cloud(),
                "decisions": [d.as_dict() for d in self.decisions.values()],
                "skipped": {v: r for v in EXPANSION if (r := self.skip_reason(v))}}


def make_plan(ws: Any, cfgs: Mapping[str, Any], verbs: list[str], follow: bool = True,
              given: Mapping[str, Any] | None = None, table: list[dict[str, str]] | None = None) -> Plan:
    """The decisions that the inputs make for the stages ``verbs`` of a run on workspace ``ws`` with the
    resolved options ``cfgs`` (verb → config). Reads cloud_ldr.ply (when an expansion stage, build-bsh or
    relight is in ``verbs``), the object and scene.json (when relight is) and, when present, reproject's and
    build-bsh's outputs for the decisions they make. ``given``: verb → the option names the run's TOML sets
    (they are not decided again); ``table``: the measured relight table (default :func:`read_table`)."""
    from .. import io

    p = Plan(follow=follow, unseen=cfgs["reproject"].unseen if "reproject" in cfgs else "poisson")
    c = None
    if any(v in verbs for v in (*EXPANSION, "build-bsh")):
        if ws.cloud_ldr.exists():
            c = io.read_cloud(ws.cloud_ldr)
            p.set(decide_expansion(c.colors, cfgs["reproject"].t_l))
        else:
            p.set(pending("expansion", EXPANSION, f"not decided: {ws.cloud_ldr} is absent", "plan"))
    ex = p.get("expansion")
    if ex is not None and ex.needed is not False and any(v in verbs for v in (*FACES, "reproject")):
        rules = faces_rules(cfgs)
        known = None if "expose-match" in verbs or not ws.exposure.exists() else _registered(ws.exposure)
        p.set(decide_faces(rules, known, cfgs["reproject"].unseen))
    if ex is not None and ex.needed is not False and any(v in verbs for v in ("poisson", "build-bsh")):
        p.set(pending("poisson", ("poisson",), "runs if reproject leaves a point invalid (decided after reproject)",
                      "after reproject"))
    if "build-bsh" in verbs:
        p.set(pending("emitters", ("build-bsh", "relight"),
                      f"emitters decided by build-bsh (--emitters {cfgs['build-bsh'].emitters})", "build-bsh"))
    if "relight" in verbs:
        rc = cfgs["relight"]
        g = p.set(decide_glossy(io.read_object(ws.object), rc))
        mine = set((given or {}).get("relight", ()))
        tab = read_table() if table is None else table
        p.set(decide_microbuffer(tab, g.value["brdf"], rc.microbuffer, rc.preset, "microbuffer" in mine))
        geom = _object_geometry(ws, rc, None if c is None else c.points) \
            if rc.method == "hybrid" and "omega_tr" not in mine else None
        p.set(decide_cut(tab, rc.method, rc.omega_tr, geom, "omega_tr" in mine))
    return p


def _object_geometry(ws: Any, rc: Any, cloud_points: np.ndarray | None = None) -> dict[str, float] | None:
    """:func:`object_geometry` of the run's object (placed by scene.json), camera (relight's view and size) and
    cloud (cloud_ldr.ply: the points every HDR cloud keeps); None when a file is missing."""
    from .. import io
    from ..relight.gbuffer import place_parts
    from ..relight.inputs import camera_for, objects_for

    if not (ws.cloud_ldr.exists() and ws.scene.exists() and ws.object.exists()):
        return None
    scene = io.read_json(ws.scene)
    cam = camera_for(rc, scene, ws.scene, ws.view)
    pts = np.concatenate([q["positions"] for path, w in objects_for(ws.object, scene, ws.scene)
                          for q in place_parts(io.read_object(path), w)])
    if cloud_points is None:
        cloud_points = io.read_cloud(ws.cloud_ldr, estimate_missing_normals=False).points
    return object_geometry(pts, cloud_points, cam)


def _registered(exposure: Path) -> bool:
    from ..expansion.photo_set import registered

    return registered(exposure)


def faces_from_file(p: Plan, exposure: Path) -> Decision | None:
    """Make the faces decision from ``exposure.npz`` when it exists (None otherwise)."""
    fa = p.get("faces")
    if fa is None or fa.needed is not None or not Path(exposure).exists():
        return None
    return p.set(decide_faces([], _registered(exposure), p.unseen))


def poisson_from_file(p: Plan, cloud_proj: Path) -> Decision | None:
    """Make the poisson decision from ``cloud_proj.ply`` when it exists (None otherwise)."""
    from .. import io

    if not Path(cloud_proj).exists():
        return None
    return p.set(decide_poisson(io.read_cloud(cloud_proj, estimate_missing_normals=False).valid))


def emitters_from_file(p: Plan, bsh_json: Path) -> Decision | None:
    """Record build-bsh's emitter decision from its report when it exists (None otherwise)."""
    from .. import io

    if not Path(bsh_json).exists():
        return None
    rep = io.read_json(bsh_json)
    return p.set(record_emitters(rep)) if isinstance(rep, dict) else None
