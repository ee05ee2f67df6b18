#version 430
// cut.geom.glsl — one iteration of the Mipmapped / Hybrid PBGI traversal (paper 000 §5.2.1,
// §5.2.2, Fig. 7) over (node, pixel) pairs, run under transform feedback with two vertex streams:
//   stream 0 → pairs to refine further (the next iteration's input, ping-pong buffer),
//   stream 1 → finished pairs: mipmapped: (level-0 pixel, node that the classic walk would splat at
//              once: stop rule or leaf); hybrid: (pixel at any level, sub-tree root handed to the
//              classic walk for every level-0 pixel below it — expanded on the CPU).
// A pixel code is (level << 27) | Z-order (Morton) index at that level; the four children of code c at
// level l are 4c..4c+3 at level l−1.
//
// Exactness: at level 0 the decision is the classic walk's, line for line (walk.comp.glsl: horizon and
// back-face culls, Eq. 4, stop rule). At a coarse level a pair's node is only refined when EVERY level-0
// receiver below the pixel would refine it in the classic walk (not culled, stop rule false, not a leaf),
// and only dropped when EVERY receiver below culls it; everything else splits the pixel. So the cut of
// every receiver equals the classic cut (mipmapped), or the hand-off node is one the classic walk reaches
// (hybrid). The receivers below a coarse pixel lie in a sphere (centre cp, radius rp) and their normals in a
// cone (axis w, half-angle γ); the bounds below take both into account (Minkowski enlargement of Eq. 6–8).
// Counters (MipCount): mip_count[0] pairs on stream 0, mip_count[1] pairs on stream 1.
#include "pbgi_common.glsl"

layout(points) in;
layout(points, max_vertices = 5) out;
in uvec2 v_pair[];
layout(stream = 0) out uvec2 o_next;
layout(stream = 1) out uvec2 o_done;

layout(std430, binding = PBGI_BIND_MIP_CONE) readonly buffer MipCone { vec4 mip_cone[]; };     // axis.xyz, cos γ' (level 0: normal, 1)
layout(std430, binding = PBGI_BIND_MIP_SPHERE) readonly buffer MipSphere { vec4 mip_sph[]; };    // centre.xyz, radius (< 0: empty)
layout(std430, binding = PBGI_BIND_MIP_COUNT) buffer MipCount { uint mip_count[4]; };

uniform uint level_off[16];   // first entry of each level in the Morton-ordered pyramid buffers
uniform float stop_multiple;  // §5.3 stop rule multiple (4)
uniform float omega_pix;      // Eq. 5: 2π/m²
uniform float omega_tr;       // hybrid hand-off threshold Ω_tr = omega_tr_multiple · Ω_pix [sr]
uniform int hybrid;           // 0 mipmapped, 1 hybrid
uniform float rel_eps;        // relative safety margin of the coarse-level tests
uniform float norm_eps;       // max | |n| − 1 | of the tile's normals: dot(v, n) differs from dot(v, n̂) by ≤ norm_eps·|v|

const uint LEVEL_SHIFT = 27u;
const uint CODE_MASK = (1u << 27u) - 1u;
const float HALF_PI = 0.5 * float(PBGI_PI);

void emit_next(uint node, uint pix) {
    o_next = uvec2(node, pix);
    atomicAdd(mip_count[0], 1u);
    EmitStreamVertex(0);
    EndStreamPrimitive(0);
}

void emit_done(uint node, uint pix) {
    o_done = uvec2(node, pix);
    atomicAdd(mip_count[1], 1u);
    EmitStreamVertex(1);
    EndStreamPrimitive(1);
}

void main() {
    uint node = v_pair[0].x;
    uint pix = v_pair[0].y;
    uint level = pix >> LEVEL_SHIFT;
    uint code = pix & CODE_MASK;
    Node nd = pbgi_nodes[node];
    bool leaf = pbgi_is_leaf(nd);
    vec4 pc = mip_cone[level_off[level] + code];
    vec4 ps = mip_sph[level_off[level] + code];

    if (level == 0u) {
        // --- the classic walk's decision for one receiver (walk.comp.glsl) ---
        vec3 p = ps.xyz;
        vec3 n = pc.xyz;
        vec3 v = pbgi_center(nd) - p;
        float dist = length(v);
        if (pbgi_horizon_cull(v, nd.radius, n) || pbgi_backface_cull(v, dist, nd.radius, nd.cone)) return;
        if (hybrid != 0) { emit_done(node, pix); return; }           // classic walk from this sub-tree
        float om = pbgi_node_solid_angle(dist, nd.radius);
        if (pbgi_stop(om, leaf, stop_multiple, omega_pix)) { emit_done(node, pix); return; }  // splat at once
        emit_next(node + 1u, pix);                                    // Fig. 7a at level 0: both children
        emit_next(nd.right, pix);
        return;
    }

    // --- coarse pixel: receivers in the sphere (cp, rp), normals in the cone (w, γ') ---
    // Only +, −, ×, /, sqrt here (no acos/asin/cos: llvmpipe's approximations differ from numpy's by
    // up to ~1e-4, and the CPU simulation must take the same decisions). cos γ' is stored per pixel
    // (γ' = γ + ang_eps), cos/sin of the node cones' half-angles come from a table.
    vec3 c = pbgi_center(nd);
    float r = nd.radius;
    vec3 w = pc.xyz;
    float cg = pc.w;
    float sg = sqrt(max(1.0 - cg * cg, 0.0));
    vec3 cp = ps.xyz;
    float rp = ps.w;
    vec3 D = c - cp;
    float d = length(D);
    float len_eps = rel_eps * (d + r + rp) + norm_eps * (d + rp);

    // horizon cull (dot(c − x, n) < −r): bounds of dot(c − x, n) over x in the sphere, n in the cone.
    // d·cos(φ ∓ γ') = dw·cos γ' ± d·sin φ·sin γ', dw = d·cos φ.
    float dw = dot(w, D);
    float dsin = sqrt(max(d * d - dw * dw, 0.0));
    float dot_max = (dw >= d * cg ? d : dw * cg + dsin * sg) + rp;
    float dot_min = (dw <= -d * cg ? -d : dw * cg - dsin * sg) - rp;
    bool hz_all = dot_max + len_eps < -r;                  // Eq. 8 with α = asin((r + rp)/d): culled for all
    bool hz_none = dot_min - len_eps >= -r;                // culled for none

    // back-face cull (Fig. 5, pbgi_backface_cull): x culled iff dot(x − c, a) < −|x − c|·sin(half + δx),
    // δx = asin(r/|x − c|), when half + δx < π/2 (else never). |x − c| ∈ [d − rp, d + rp].
    uint abyte = nd.cone >> 24u;
    bool all_dirs = abyte == 255u;
    vec3 ax; float hlf;
    pbgi_cone_decode(nd.cone, ax, hlf);
    vec2 hcs = pbgi_cone_trig[abyte];                      // (cos half, sin half)
    float ua = -dot(D, ax);                                // dot(cp − c, a)
    bool bf_none = all_dirs || abyte >= 128u || d + rp + len_eps <= r;
    if (!bf_none && d > rp + len_eps) {
        float sd = min(r / (d + rp), 1.0);                 // sin δ_min
        float smin = hcs.y * sqrt(max(1.0 - sd * sd, 0.0)) + hcs.x * sd;   // sin(half + δ_min)
        bf_none = ua - rp + (d - rp) * smin - len_eps >= 0.0;
    }
    bool bf_all = false;
    if (!all_dirs && abyte < 128u && d - rp > r + len_eps) {
        float sd = min(r / (d - rp), 1.0);                 // sin δ_max
        float cdl = sqrt(max(1.0 - sd * sd, 0.0));
        float cmax = hcs.x * cdl - hcs.y * sd;             // cos(half + δ_max) > 0: lim < π for all x
        float smax = hcs.y * cdl + hcs.x * sd;             // sin(half + δ_max)
        bf_all = cmax > rel_eps && ua + rp + (d + rp) * smax + len_eps < 0.0;
    }
    if (hz_all || bf_all) return;                              // culled for every receiver below

    float om_c = pbgi_node_solid_angle(d, r);                  // Eq. 4 from the pixel's centre
    if (hybrid != 0 && om_c < omega_tr) { emit_done(node, pix); return; }   // §5.2.2 hand-off

    // stop rule false for every receiver: Ω at the farthest receiver (d + rp) still above the limit
    bool refine_all = !leaf && pbgi_node_solid_angle(d + rp, r) > stop_multiple * omega_pix * (1.0 + rel_eps);
    bool can_refine = refine_all && hz_none && bf_none;
    float om_p = float(PBGI_TWO_PI) * (1.0 - cg);          // Ω(p_j) = 2π(1 − cos γ)
    if (can_refine && om_c > om_p) {                           // Fig. 7a: the node is the bigger one
        emit_next(node + 1u, pix);
        emit_next(nd.right, pix);
        return;
    }
    // Fig. 7b: next mip level, the four children of the pixel (empty ones skipped)
    uint cl = level - 1u;
    uint cbase = level_off[cl] + 4u * code;
    for (uint k = 0u; k < 4u; ++k) {
        if (mip_sph[cbase + k].w >= 0.0) emit_next(node, (cl << LEVEL_SHIFT) | (4u * code + k));
    }
}
