#version 430
// importance.comp.glsl — importance-driven point projection (paper 001 §3.2): fill receiver k's micro-buffer
// (the shared m×m hemispherical layout of walk.comp.glsl, so eq9.comp.glsl gathers it) from point samples
// of the cloud's clusters instead of a walk of the BSH.
//   phase 0: per cluster c: a cluster of the receiving object's own surfels (root ≥ object_first) is splatted whole,
//            every surfel as the walk splats a leaf (its culls, disc or sphere, fallback texel: its occlusion of
//            itself has no holes and is classic's); a cluster whose root node the walk's
//            stop rule would stop at (Ω ≤ stop_multiple · omega_pix: a far cluster, the sun split off by
//            bsh_clusters' contrast rule) is splatted as that node, once, as the walk splats it (pbgi_splat_node), and
//            one the walk culls (below the horizon, facing away) is skipped — these three are marked done (imp −1);
//            the others: n_random uniform random points give its importance (Eq. 1, × the BRDF's luminance for a
//            glossy receiver, Eq. 4) summed into imp[k·C + c] (× |C_c|/n_random: clusters differ in size here) and
//            the total. Nothing of theirs is splatted yet.
//   phase 1: the GPU-friendly budget assignment of 001 §3.2 in its cumulative form (assign_budget in
//            importance.py, its twin): n_c = the samples of cluster c so that exactly n_budget are drawn; the
//            n_random points of phase 0 (the same random numbers) and the n_c drawn ones are splatted with Eq. 3
//            over both draws: Ω_s = |C_c| ΔA_s / (N_rd + N_s p_c) · |cos θ_s| / d² — the cluster's expected
//            points together tile its footprint. (001 splats the random points in phase 0 with N_s p_c = N_s / C:
//            here 8 budgeted a cluster against 2 random, so that a near cluster's 2 random points each covered
//            half its solid angle as one square, over whatever lies beyond it; 128 clusters × 8 samples left the
//            white furnace −22 % dark and the shipped view1 +12 %.)
//   phase 2: exhaustive (tests): every point of every cluster, Ω_s = ΔA_s |cos θ_s| / d².
// The splat: a square of side ⌈√(Ω_s / Ω_texel)⌉ texels (≥ 1, ≤ splat_max) around the sample's direction,
// depth-tested (nearest wins). ⌈⌉, not round: a splat covers at least its Ω_s (fewer holes: the white furnace at 512
// clusters × 8 −0.8 %). Each texel's depth is the walk's key, dist + λ·d⊥ (PBGI_LAMBDA, relight's
// --splat-lambda; d⊥ the sample's distance from the texel's ray): among one surface's overlapping squares the
// sample nearest the ray wins, not the one nearest the receiver. ΔA_s = area_scale · π r_s² (importance.py).
// The object's surfels (nodes ≥ object_first) are not points: they obey the walk's near-field rule (object_near,
// object_reach on recv_e, the geometric plane), its horizon and back-face culls, its leaf splat (pbgi_splat_node)
// and give their directional radiance (obj_dir), as in walk.comp.glsl.
// Resumable like the walk: at most iter_budget loop iterations a receiver and dispatch (llvmpipe's loop limit),
// the progress in istate; receivers not finished bump `pending`.
// Buffers: nodes (the points are leaves), micro-buffers, texel table, recv_a..d (walk.py), start_off = cluster
// offsets (C+1) then the C cluster root nodes, start_node = the leaves' node indices grouped by cluster, splat
// (ΔA_s = area_scale · π r_s²),
// istate (2 uvec4 a receiver), imp (C floats a receiver), pending.


#define PBGI_MICROBUFFER
#include "pbgi_common.glsl"
#include "brdf.glsl"

layout(local_size_x = 64) in;
layout(std430, binding = PBGI_BIND_START_OFF) readonly buffer ClusterOff { uint cluster_off[]; };
layout(std430, binding = PBGI_BIND_START_NODE) readonly buffer ClusterPts { uint cluster_pts[]; };
layout(std430, binding = PBGI_BIND_PENDING) buffer Pending { uint pending; };
layout(std430, binding = PBGI_BIND_SPLAT) readonly buffer Splat { float splat_radius[]; };
layout(std430, binding = PBGI_BIND_RECV_C) readonly buffer RecvC { vec4 recv_c[]; };
layout(std430, binding = PBGI_BIND_RECV_D) readonly buffer RecvD { vec4 recv_d[]; };
layout(std430, binding = PBGI_BIND_ISTATE) buffer IState { uvec4 istate[]; };
layout(std430, binding = PBGI_BIND_IMP) buffer Imp { float imp[]; };

uniform uint n_recv;
uniform uint first;
uniform int m;
uniform uint n_clusters;    // C
uniform uint n_random;      // random points a cluster (phase 0)
uniform uint n_budget;      // N_s
uniform uint seed;
uniform int init;           // 1 on the first pass
uniform int exhaustive;     // 1: phase 2 only
uniform int iter_budget;
uniform int splat_max;      // the largest splat side [texels]
uniform int brdf_kind;
uniform int masking;
uniform float area_scale;   // ΔA_s = area_scale · π r_s² (r_s = d₄/√2: 2/π gives d₄², a grid point's area)
uniform uint object_first;  // nodes from here on are the receiving object's surfels: the walk's near-field rule
uniform float object_near;  // (walk.comp.glsl): an object leaf lower than object_near × its splat radius above
uniform float object_reach; // the receiver's geometric plane and within object_reach × it is not splatted
uniform int obj_dir_side;   // a glossy object's directional surfel radiance (walk.comp.glsl node_radiance)
layout(std430, binding = PBGI_BIND_OBJ_DIRS) readonly buffer ObjDirs { vec4 obj_dir[]; };
uniform float stop_multiple; // the walk's stop rule: a cluster whose root node subtends ≤ stop_multiple · omega_pix
uniform float omega_pix;     // is splatted as that node, once (the walk's cut), and draws no samples
uniform float disc_cone;

const uint NONE = 0xFFFFFFFFu;

uint pcg(uint v) {
    uint s = v * 747796405u + 2891336453u;
    uint w = ((s >> ((s >> 28u) + 4u)) ^ s) * 277803737u;
    return (w >> 22u) ^ w;
}
float u01(uint key, uint c, uint j, uint what) {
    return float(pcg(key ^ pcg(c ^ pcg(j * 4u + what))) >> 8u) * (1.0 / 16777216.0);
}

// Splat node i (a leaf) seen from p with frame (t, b, n); omega_s = Eq. 3's solid angle. Returns the texels written.
int splat_point(uint base, vec3 v, float dist, vec3 t, vec3 b, vec3 n, float omega_s, vec3 color) {
    vec3 l = vec3(dot(v, t), dot(v, b), dot(v, n)) / dist;
    if (l.z <= 0.0) return 0;
    ivec2 uv = pbgi_dir_texel(l, m);
    float om_t = pbgi_texel[uv.y * m + uv.x].z;
    if (!(om_t > 0.0)) om_t = float(PBGI_TWO_PI) / float(m * m);
    int side = clamp(int(ceil(sqrt(omega_s / om_t))), 1, splat_max);
    ivec2 lo = ivec2(floor((l.xy + 1.0) * 0.5 * float(m) - 0.5 * float(side) + 0.5));
    int w = 0;
    for (int q = 0; q < side * side; ++q) {
        ivec2 xy = lo + ivec2(q % side, q / side);
        if (any(lessThan(xy, ivec2(0))) || any(greaterThanEqual(xy, ivec2(m)))) continue;
        vec4 tx = pbgi_texel[xy.y * m + xy.x];
        float cw = dot(pbgi_xy_dir(tx.xy), l);          // the walk's depth key: + λ × the sample's distance from the
        pbgi_splat_texel(base + uint(xy.y * m + xy.x), // texel's ray (among one surface's samples, the nearest the ray)
                         dist + PBGI_LAMBDA * dist * sqrt(max(1.0 - cw * cw, 0.0)), color);
        w++;
    }
    return w + 1;
}

void main() {
    uint k = first + gl_GlobalInvocationID.x;
    if (k >= n_recv) return;
    // istate[2k] = (phase, cluster, sample j, n_c or NONE); istate[2k+1] = (Σ importance, cumulative importance,
    // budgeted samples drawn, points splatted)   (floats as bits)
    uvec4 s0 = init != 0 ? uvec4(exhaustive != 0 ? 2u : 0u, 0u, 0u, NONE) : istate[2u * k];
    uvec4 s1 = init != 0 ? uvec4(floatBitsToUint(0.0), floatBitsToUint(0.0), 0u, 0u) : istate[2u * k + 1u];
    uint phase = s0.x, c = s0.y, j = s0.z, nk = s0.w;
    float total = uintBitsToFloat(s1.x), cum = uintBitsToFloat(s1.y);
    uint drawn = s1.z, splats = s1.w;
    if (phase == 3u) return;

    vec3 p = recv_a[k].xyz;
    vec3 n = recv_b[k].xyz;
    vec3 t, b;
    pbgi_frame(n, t, b);
    vec3 wo = recv_d[k].xyz;
    vec3 wl = normalize(vec3(dot(wo, t), dot(wo, b), max(dot(wo, n), 1e-4)));
    vec3 albedo = recv_c[k].rgb;
    float rough = recv_a[k].w, metal = recv_b[k].w;
    uvec3 pb = floatBitsToUint(p);
    uint key = pcg(seed ^ pcg(pb.x ^ pcg(pb.y ^ pcg(pb.z))));
    uint base = k * uint(m * m);
    uint C = n_clusters;
    float Ns = float(n_budget);
    int iters = 0;
    while (iters < iter_budget) {
        iters++;
        if (phase == 0u) {
            if (c >= C) { phase = 1u; c = 0u; j = 0u; nk = NONE; continue; }
            bool own = nk == 1u;                           // a cluster of the object's own surfels: every one
            if (j >= (own ? cluster_off[c + 1u] - cluster_off[c] : n_random)) { c++; j = 0u; nk = NONE; continue; }
            if (j == 0u && nk == NONE) {
                imp[k * C + c] = 0.0;
                uint ci = cluster_off[C + 1u + c];
                if (ci >= object_first) { imp[k * C + c] = -1.0; nk = 1u; continue; }   // splatted whole here: its
                                                               // occlusion has no holes; DONE for phase 1
                Node cn = pbgi_nodes[ci];                      // the cluster's root node
                vec3 cv = pbgi_center(cn) - p;
                float cd = length(cv);
                if (pbgi_horizon_cull(cv, cn.radius, n) || pbgi_backface_cull(cv, cd, cn.radius, cn.cone)) {
                    imp[k * C + c] = -1.0; c++; continue;     // the walk culls it: nothing of it is seen
                }
                if (pbgi_stop(pbgi_node_solid_angle(cd, cn.radius), false, stop_multiple, omega_pix)) {
                    vec3 cax; float cha;
                    pbgi_cone_decode(cn.cone, cax, cha);
                    vec3 vl = vec3(dot(cv, t), dot(cv, b), dot(cv, n));
                    vec3 al = vec3(dot(cax, t), dot(cax, b), dot(cax, n));
                    iters += pbgi_splat_node(base, m, vl, cd, splat_radius[ci], al, cha <= disc_cone, pbgi_color(cn));
                    splats++;
                    imp[k * C + c] = -1.0; c++; continue;     // the walk's cut: no samples
                }
            }
        } else if (phase == 1u) {
            if (c >= C) { phase = 3u; break; }
            if (nk == NONE) {                      // 001 §3.2's assignment, cumulative form (assign_budget)
                float ik = max(imp[k * C + c], 0.0);
                cum += ik;
                float e = total > 0.0 ? Ns * min(cum / total, 1.0) : 0.0;
                float fk = e - float(drawn);
                nk = 0u;
                if (ik > 0.0) {
                    float fl = floor(max(fk, 0.0));
                    nk = uint(fl);
                    if (u01(key, c, 0u, 3u) < fk - fl) nk++;
                }
                drawn += nk;
                j = 0u;
                if (imp[k * C + c] < 0.0) { c++; nk = NONE; continue; }   // done in phase 0
            }
            if (j >= n_random + nk) { c++; j = 0u; nk = NONE; continue; }
        } else if (phase == 2u) {
            if (c >= C) { phase = 3u; break; }
            if (j >= cluster_off[c + 1u] - cluster_off[c]) { c++; j = 0u; continue; }
        } else {
            break;
        }
        uint o0 = cluster_off[c], cnt = cluster_off[c + 1u] - o0;
        bool every = phase == 2u || (phase == 0u && nk == 1u);
        // phase 1 draws the n_random points of phase 0 again (the same numbers), then its nk budgeted ones
        uint idx = every ? j : min(uint((phase == 1u && j < n_random ? u01(key, c, j, 0u)
                                         : u01(key, c, phase == 1u ? j - n_random : j, phase)) * float(cnt)), cnt - 1u);
        uint i = cluster_pts[o0 + idx];
        Node nd = pbgi_nodes[i];
        vec3 v = pbgi_center(nd) - p;
        float dist = length(v);
        j++;
        if (!(dist > 0.0)) continue;
        vec3 ax; float half_angle;
        pbgi_cone_decode(nd.cone, ax, half_angle);
        float rs = splat_radius[i];
        float dA = area_scale * float(PBGI_PI) * rs * rs;
        float cos_s = abs(dot(ax, v)) / dist;
        float cos_p = dot(n, v) / dist;
        float proj = dA * cos_s / (dist * dist);  // ΔA_s |cos θ_s| / d²  [sr]
        if (phase == 0u && !every) {              // importance only: the points are splatted in phase 1
            float w = max(cos_p, 0.0) * proj * float(cnt) / float(n_random);    // Eq. 1 (× |C_c| / N_rd)
            if (brdf_kind != BRDF_LAMBERT && w > 0.0) {                       // Eq. 4
                vec3 wi = vec3(dot(v, t), dot(v, b), dot(v, n)) / dist;
                vec3 f = brdf_eval(brdf_kind, masking, wi, wl, vec3(0.0, 0.0, 1.0), albedo, metal, rough);
                w *= dot(f, vec3(0.2126, 0.7152, 0.0722));
            }
            imp[k * C + c] += w;
            total += w;
            continue;
        }
        // Eq. 3 over both draws: the cluster's expected points, N_rd + N_s p_c (the random and the budgeted ones
        // together tile its footprint; 001 splats the random ones as if N_s p_c = N_s / C, so that a near
        // cluster's 2 random points each covered half its solid angle as a square, over what lies beyond it)
        float omega_s = every ? proj
                              : float(cnt) * proj / (float(n_random) + (total > 0.0 ? Ns * imp[k * C + c] / total : 0.0));
        // a point seen from behind occludes (001 §3.2: it casts indirect shadows) but its radiance towards p is not
        // known: black. (Its own colour: 200 receivers in the shipped room +3 % brighter still against classic; culled as
        // the walk does: +6 %, the room behind a thin surface shows through.)
        bool back = dot(ax, v) > 0.0 && half_angle < 1.5;
        bool near = i >= object_first && dot(v, recv_e[k].xyz) < object_near * rs && dist < object_reach * rs;
        if (i >= object_first) {                  // the object's own surfels: the walk's leaf splat (its culls, its
            // disc or sphere of radius r_s, its fallback texel), not a point's square: ⌈⌉-rounded squares of near
            // surfels overlapped past the object's silhouette (the lamp room's view2: classic 0.975, importance
            // 0.962 of full_*, 0.972 splatted as the walk splats them, see docs/relight.md)
            if (!near && !pbgi_horizon_cull(v, nd.radius, n) && !pbgi_backface_cull(v, dist, nd.radius, nd.cone)) {
                vec3 col = obj_dir_side > 0
                    ? obj_dir[(i - object_first) * uint(obj_dir_side * obj_dir_side) + pbgi_oct_cell(-v / dist, obj_dir_side)].rgb
                    : pbgi_color(nd);
                vec3 vl = vec3(dot(v, t), dot(v, b), dot(v, n));
                vec3 al = vec3(dot(ax, t), dot(ax, b), dot(ax, n));
                iters += pbgi_splat_node(base, m, vl, dist, rs, al, half_angle <= disc_cone, col);
                splats++;
            }
        } else if (cos_p > 0.0) {
            iters += splat_point(base, v, dist, t, b, n, omega_s, back ? vec3(0.0) : pbgi_color(nd));
            splats++;
        }
    }
    istate[2u * k] = uvec4(phase, c, j, nk);
    istate[2u * k + 1u] = uvec4(floatBitsToUint(total), floatBitsToUint(cum), drawn, splats);
    if (phase != 3u) atomicAdd(pending, 1u);
}
