#version 430
// importance.comp.glsl — importance-driven point projection (paper 001 §3.2): fill receiver k's micro-buffer
// (the shared m×m hemispherical layout of walk.comp.glsl, so eq9.comp.glsl gathers it) from point samples
// of the cloud's clusters instead of a walk of the BSH.
//   phase 0: per cluster c, n_random uniform random points: importance (Eq. 1, × the BRDF's luminance for a
//            glossy receiver, Eq. 4) summed into imp[k·C + c] (× |C_c|/n_random: clusters differ in size here)
//            and the total; each point splatted with Eq. 3, p_c = 1/C (001 §3.2 Summary).
//   phase 1: the GPU-friendly budget assignment of 001 §3.2 in its cumulative form (assign_budget in
//            importance.py, its twin): n_c = the samples of cluster c so that exactly n_budget are drawn;
//            each drawn point splatted with Eq. 3.
//   phase 2: exhaustive (tests): every point of every cluster, Ω_s = ΔA_s |cos θ_s| / d².
// Eq. 3: Ω_s = |C_c| ΔA_s / (N_s p_c) · |cos θ_s| / d²; the splat is a square of side ⌈√(Ω_s / Ω_texel)⌉ texels
// (≥ 1, ≤ splat_max) around the sample's direction, depth-tested (nearest wins). ⌈⌉, not round: a splat covers at
// least its Ω_s (white furnace at 512 clusters × 4: −3.1 % mean with ⌈⌉, −4.6 % with round — the holes).
// Resumable like the walk: at most iter_budget loop iterations a receiver and dispatch (llvmpipe's loop limit),
// the progress in istate; receivers not finished bump `pending`.
// Buffers: nodes (the points are leaves), micro-buffers, texel table, recv_a..d (walk.py), start_off = cluster
// offsets (C+1) into start_node = the leaves' node indices grouped by cluster, splat (ΔA_s = π r_s²),
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
        pbgi_splat_texel(base + uint(xy.y * m + xy.x), dist, color);
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
            if (j >= n_random) { c++; j = 0u; continue; }
            if (j == 0u) imp[k * C + c] = 0.0;
        } else if (phase == 1u) {
            if (c >= C) { phase = 3u; break; }
            if (nk == NONE) {                      // 001 §3.2's assignment, cumulative form (assign_budget)
                float ik = imp[k * C + c];
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
            }
            if (j >= nk) { c++; j = 0u; nk = NONE; continue; }
        } else if (phase == 2u) {
            if (c >= C) { phase = 3u; break; }
            if (j >= cluster_off[c + 1u] - cluster_off[c]) { c++; j = 0u; continue; }
        } else {
            break;
        }
        uint o0 = cluster_off[c], cnt = cluster_off[c + 1u] - o0;
        uint idx = phase == 2u ? j : min(uint(u01(key, c, j, phase) * float(cnt)), cnt - 1u);
        uint i = cluster_pts[o0 + idx];
        Node nd = pbgi_nodes[i];
        vec3 v = pbgi_center(nd) - p;
        float dist = length(v);
        j++;
        if (!(dist > 0.0)) continue;
        vec3 ax; float half_angle;
        pbgi_cone_decode(nd.cone, ax, half_angle);
        float rs = splat_radius[i];
        float dA = float(PBGI_PI) * rs * rs;
        float cos_s = abs(dot(ax, v)) / dist;
        float cos_p = dot(n, v) / dist;
        float proj = dA * cos_s / (dist * dist);  // ΔA_s |cos θ_s| / d²  [sr]
        float omega_s;
        if (phase == 0u) {
            float w = max(cos_p, 0.0) * proj * float(cnt) / float(n_random);    // Eq. 1 (× |C_c| / N_rd)
            if (brdf_kind != BRDF_LAMBERT && w > 0.0) {                       // Eq. 4
                vec3 wi = vec3(dot(v, t), dot(v, b), dot(v, n)) / dist;
                vec3 f = brdf_eval(brdf_kind, masking, wi, wl, vec3(0.0, 0.0, 1.0), albedo, metal, rough);
                w *= dot(f, vec3(0.2126, 0.7152, 0.0722));
            }
            imp[k * C + c] += w;
            total += w;
            omega_s = float(cnt) * proj * float(C) / Ns;                       // Eq. 3 with p_c = 1/C
        } else if (phase == 1u) {
            float pk = imp[k * C + c] / total;
            omega_s = float(cnt) * proj / (Ns * pk);                           // Eq. 3
        } else {
            omega_s = proj;
        }
        // a point seen from behind occludes (001 §3.2: it casts indirect shadows) but its radiance towards p is not
        // known: black. (Its own colour: 200 receivers in the shipped room +3 % brighter still against classic; culled as
        // the walk does: +6 %, the room behind a thin surface shows through.)
        bool back = dot(ax, v) > 0.0 && half_angle < 1.5;
        if (cos_p > 0.0) {
            iters += splat_point(base, v, dist, t, b, n, omega_s, back ? vec3(0.0) : pbgi_color(nd));
            splats++;
        }
    }
    istate[2u * k] = uvec4(phase, c, j, nk);
    istate[2u * k + 1u] = uvec4(floatBitsToUint(total), floatBitsToUint(cum), drawn, splats);
    if (phase != 3u) atomicAdd(pending, 1u);
}
