// pbgi_common.glsl — shared PBGI building blocks (paper 000 §5.2–§5.4), owned by relight-core.
//
// Include it right after `#version 430` with an include line naming this file (pipeline.gl.load_glsl
// resolves it).
// Conventions: metres, radians, linear radiance float32 (never half). A "pixel" is a G-buffer receiver
// with world position p and unit shading normal n. For a node A: v = centre(A) − p (world vector from
// the receiver to the node centre), dist = |v|, r = radius(A).
//
// Optional defines (set them BEFORE the #include):
//   Binding numbers are never written in GLSL: the loader injects `#define PBGI_BIND_<NAME> <n>` from
//   pipeline/bsh/format.py (GATHER_BINDINGS, CUT_BINDINGS); a program compiled without them fails.
//   PBGI_BIND_NODES     binding of `readonly buffer PbgiNodes { Node pbgi_nodes[]; }`;
//                       define PBGI_NO_NODE_BUFFER to omit the declaration (struct + functions only).
//   PBGI_MICROBUFFER    declare the micro-buffer, texel-table and receiver (recv_a, recv_b, recv_e) SSBOs and pbgi_splat():
//     PBGI_BIND_MICROBUFFER `buffer PbgiMicroBuffer { vec4 pbgi_mb[]; }` — texel (u,v) of the
//                        micro-buffer starting at `base` is pbgi_mb[base + v*m + u] = (R, G, B, depth),
//                        float32; an empty texel is (0,0,0, PBGI_FAR).
//     PBGI_BIND_TEXELS   `readonly buffer PbgiTexels { vec4 pbgi_texel[]; }` — m*m entries,
//                        texel (u,v) at v*m+u: (x, y, omega, proj) where (x, y) are the tangent-plane
//                        coordinates of the texel's representative unit direction
//                        (z = sqrt(1 − x² − y²)), omega its solid angle [sr] and proj = ∫_texel cos dω
//                        (the factor Ω_ij·(n·ω_ij) of Eq. 9). omega == 0 marks an unused texel.
//                        Built on the CPU by pipeline.gather.walk.texel_table(m, mode):
//                        mode "exact": every texel that meets the unit disc is used; omega = ∫∫ dxdy/z over
//                        texel ∩ disc (exact), proj = area(texel ∩ disc) (exact), direction = the mean
//                        direction over the texel (normalised); for interior texels ≈ the texel centre.
//                        mode "paper": texels whose centre is inside the disc, direction = centre,
//                        omega = 2π/m² (Eq. 5, substituted for the node's as §5.3), proj = omega·z_centre.
//
// Functions (all pure unless stated):
//   struct Node                      40-byte std430 node of bsh.npz (pipeline/bsh/format.py NODE_DTYPE).
//   bool  pbgi_is_leaf(Node)         right == 0xFFFFFFFF.
//   vec3  pbgi_center(Node), pbgi_color(Node)
//   void  pbgi_cone_decode(uint cone, out vec3 axis, out float half_angle)
//                                    RGBA8 little-endian: axis = normalize(RGB/255*2−1), half = A/255·π;
//                                    A == 255 (half ≥ π) means "all directions".
//   float pbgi_node_solid_angle(float dist, float r)
//                                    Eq. 4: 2π(1 − sqrt(dist² − r²)/dist), evaluated in the cancellation-free
//                                    form 2π·s²/(1 + sqrt(1 − s²)), s = r/dist. Receiver inside or on the
//                                    sphere (dist ≤ r) → 2π (always refine; a leaf then covers the whole
//                                    hemisphere).
//   float pbgi_pixel_solid_angle(int m)   Eq. 5: 2π/m² (the stop rule's Ω_pix for an m×m micro-buffer).
//   bool  pbgi_horizon_cull(vec3 v, float r, vec3 n)
//                                    true if the node sphere lies entirely below the receiver's tangent
//                                    plane: dot(v, n) < −r.
//   bool  pbgi_horizon_cull_cone(vec3 v, float dist, float r, vec3 axis, float gamma)
//                                    Eq. 6–8 generalisation for a receiver whose normals fill a cone
//                                    (axis, half-angle gamma): cull if φ − asin(r/dist) > gamma + π/2 with
//                                    φ = angle(axis, v). gamma = 0 is the horizon cull. Never culls when
//                                    dist ≤ r.
//   bool  pbgi_backface_cull(vec3 v, float dist, float r, uint cone)
//                                    Fig. 5: cull if every normal of the node's cone faces away from the
//                                    receiver: angle(−v, axis) > half + π/2 + asin(r/dist). The asin term
//                                    (node extent) makes the test conservative; the paper's literal test
//                                    is the same without it. Never culls when dist ≤ r or half ≥ π.
//                                    Without trigonometry: cos/sin of half from the uniform table
//                                    pbgi_cone_trig (the host sets it), of δ = asin(r/dist) as r/dist and
//                                    its cosine (llvmpipe evaluated asin and cos per node visit).
//   bool  pbgi_stop(float omega_node, bool leaf, float stop_multiple, float omega_pix)
//                                    §5.3 stop rule: leaf || omega_node ≤ stop_multiple·omega_pix
//                                    (stop_multiple = 4 in the paper).
//   int   pbgi_splat_disc(uint base, int m, vec3 vloc, float dist, float r, vec3 aloc, vec3 color)
//                                    [PBGI_MICROBUFFER] the same for a flat node: the disc of radius r with
//                                    normal aloc (see its comment); relight uses it for cones ≤ --disc-cone.
//   (PBGI_LAMBDA: optional define, see pbgi_splat.)
//   (PBGI_TEXEL_UBO = m·m: optional define; the splats read the texel table from the uniform block PbgiTexelBlock,
//    bound by the host, instead of the SSBO — the same values; on llvmpipe a uniform-block read is a branch-free
//    gather, an SSBO read a per-lane loop of bounds-checked loads.)
//   void  pbgi_frame(vec3 n, out vec3 t, out vec3 b)
//                                    Duff et al. 2017 ("Building an orthonormal basis, revisited"),
//                                    right-handed: t × b = n; deterministic, branch on sign(n.z) (n.z = 0 → +).
//   vec2  pbgi_texel_xy(ivec2 uv, int m)  texel centre in [-1,1]²: x = (2u+1)/m − 1, y = (2v+1)/m − 1.
//   vec3  pbgi_xy_dir(vec2 xy)       hemisphere direction in the local frame (x, y, sqrt(1−x²−y²)).
//   vec3  pbgi_texel_dir(ivec2 uv, int m, vec3 t, vec3 b, vec3 n)   world direction of the texel centre.
//   ivec2 pbgi_dir_texel(vec3 local_dir, int m)  texel containing a local direction (x,y clamped to the grid).
//   int   pbgi_splat(uint base, int m, vec3 vloc, float dist, float r, vec3 color)   [PBGI_MICROBUFFER]
//                                    ray–sphere rasterisation of a node into the micro-buffer at `base`:
//                                    vloc = v in the receiver's (t, b, n) frame. Every used texel whose
//                                    representative direction ω hits the sphere (dot(ω, v/dist) ≥
//                                    sqrt(1 − (r/dist)²), i.e. the ray from p along ω meets the sphere; all
//                                    texels when dist ≤ r) gets (color, key) if key < its stored depth,
//                                    key = dist + PBGI_LAMBDA·d⊥, d⊥ = distance from the node centre to the
//                                    texel's ray (≤ r). PBGI_LAMBDA = 0 (default) is §5.2's depth = distance
//                                    to the node centre; relight's walk uses 4 (--splat-lambda): among the
//                                    overlapping nodes of one surface a texel then takes the node nearest its
//                                    ray rather than the one nearest the receiver (measured: halves the error
//                                    against a brute-force gather); occlusion between surfaces more than
//                                    λ·r apart is unchanged. A node covering no texel
//                                    direction (smaller than a texel) is splatted into the used texel that
//                                    contains its centre direction, when that lies above the horizon, as a
//                                    hole filler only: its depth (pbgi_fallback_depth) loses to every real
//                                    hit, so it never hides a surface a texel ray does meet (measured on
//                                    the small scene: a nearest-wins fallback biased the image +29 %).
//                                    Define PBGI_POINT_FALLBACK 0 to disable; default 1.
//                                    Returns the number of texel-loop iterations it ran (for loop budgets:
//                                    Mesa llvmpipe caps the TOTAL loop iterations of one shader invocation
//                                    — all loops, all SIMD lanes of a vector together — at 65535 and then
//                                    silently exits the loops; walk.comp.glsl therefore walks in resumable
//                                    passes). The caller owns the micro-buffer (one writer per micro-buffer,
//                                    no atomics needed).
//   const float PBGI_FAR              the empty-texel depth (3.0e38).

#ifndef PBGI_COMMON_GLSL
#define PBGI_COMMON_GLSL

#define PBGI_PI 3.14159265358979323846
#define PBGI_TWO_PI 6.28318530717958647692
#define PBGI_LEAF 0xFFFFFFFFu
const float PBGI_FAR = 3.0e38;

struct Node {
    uint right;
    uint skip;
    float cx, cy, cz;
    float r, g, b;
    float radius;
    uint cone;
};

#ifndef PBGI_NO_NODE_BUFFER
layout(std430, binding = PBGI_BIND_NODES) readonly buffer PbgiNodes { Node pbgi_nodes[]; };
#endif

bool pbgi_is_leaf(Node nd) { return nd.right == PBGI_LEAF; }
vec3 pbgi_center(Node nd) { return vec3(nd.cx, nd.cy, nd.cz); }
vec3 pbgi_color(Node nd) { return vec3(nd.r, nd.g, nd.b); }

void pbgi_cone_decode(uint cone, out vec3 axis, out float half_angle) {
    vec4 c = unpackUnorm4x8(cone);              // R = bits 0..7, ..., A = bits 24..31
    vec3 a = c.xyz * 2.0 - 1.0;
    float l = length(a);
    axis = l > 0.0 ? a / l : vec3(0.0, 0.0, 1.0);
    half_angle = (cone >> 24u) == 255u ? PBGI_PI : c.w * float(PBGI_PI);
}

float pbgi_node_solid_angle(float dist, float r) {
    if (dist <= r) return float(PBGI_TWO_PI);
    float s = r / dist;
    float s2 = s * s;
    return float(PBGI_TWO_PI) * s2 / (1.0 + sqrt(max(1.0 - s2, 0.0)));
}

float pbgi_pixel_solid_angle(int m) { return float(PBGI_TWO_PI) / float(m * m); }

bool pbgi_horizon_cull(vec3 v, float r, vec3 n) { return dot(v, n) < -r; }

bool pbgi_horizon_cull_cone(vec3 v, float dist, float r, vec3 axis, float gamma) {
    if (dist <= r) return false;
    float phi = acos(clamp(dot(axis, v) / dist, -1.0, 1.0));
    float alpha = asin(clamp(r / dist, 0.0, 1.0));
    return phi - alpha > gamma + 0.5 * float(PBGI_PI);
}

// (cos, sin) of the node cone half-angle A/255·π for every alpha byte A (bsh_format.cone_trig_table; every program
// that calls pbgi_backface_cull sets it: walk.py, cut.py)
uniform vec2 pbgi_cone_trig[256];

bool pbgi_backface_cull(vec3 v, float dist, float r, uint cone) {
    uint abyte = cone >> 24u;
    if (abyte == 255u || dist <= r) return false;
    vec2 hcs = pbgi_cone_trig[abyte];                  // (cos half, sin half)
    float sd = min(r / dist, 1.0);                     // sin δ, δ = asin(r/dist)
    float cd = sqrt(max(1.0 - sd * sd, 0.0));
    if (!(hcs.x * cd - hcs.y * sd > 0.0)) return false;   // cos(half + δ) ≤ 0: lim = half + π/2 + δ ≥ π
    vec3 axis; float half_angle;
    pbgi_cone_decode(cone, axis, half_angle);
    return dot(v, axis) > dist * (hcs.y * cd + hcs.x * sd);   // dot(−v/dist, axis) < cos(lim) = −sin(half + δ)
}

bool pbgi_stop(float omega_node, bool leaf, float stop_multiple, float omega_pix) {
    return leaf || omega_node <= stop_multiple * omega_pix;
}

void pbgi_frame(vec3 n, out vec3 t, out vec3 b) {
    float sgn = n.z >= 0.0 ? 1.0 : -1.0;
    float a = -1.0 / (sgn + n.z);
    float bb = n.x * n.y * a;
    t = vec3(1.0 + sgn * n.x * n.x * a, sgn * bb, -sgn * n.x);
    b = vec3(bb, sgn + n.y * n.y * a, -n.y);
}

// The cell of the unit world direction w in an S×S octahedral map of the sphere (surfels.py oct_cell, its twin):
// p = w.xy / |w|₁, folded over the diagonals where w.z < 0, cell = floor((p + 1)/2 · S), row-major.
uint pbgi_oct_cell(vec3 w, int S) {
    vec2 p = w.xy / max(abs(w.x) + abs(w.y) + abs(w.z), 1e-30);
    if (w.z < 0.0) p = (1.0 - abs(p.yx)) * vec2(p.x >= 0.0 ? 1.0 : -1.0, p.y >= 0.0 ? 1.0 : -1.0);
    ivec2 c = clamp(ivec2(floor((p + 1.0) * 0.5 * float(S))), ivec2(0), ivec2(S - 1));
    return uint(c.y * S + c.x);
}

vec2 pbgi_texel_xy(ivec2 uv, int m) { return (2.0 * vec2(uv) + 1.0) / float(m) - 1.0; }

vec3 pbgi_xy_dir(vec2 xy) { return vec3(xy, sqrt(max(1.0 - dot(xy, xy), 0.0))); }

vec3 pbgi_texel_dir(ivec2 uv, int m, vec3 t, vec3 b, vec3 n) {
    vec3 l = pbgi_xy_dir(pbgi_texel_xy(uv, m));
    return l.x * t + l.y * b + l.z * n;
}

ivec2 pbgi_dir_texel(vec3 local_dir, int m) {
    ivec2 uv = ivec2(floor((local_dir.xy + 1.0) * 0.5 * float(m)));
    return clamp(uv, ivec2(0), ivec2(m - 1));
}

#ifdef PBGI_MICROBUFFER
#ifndef PBGI_POINT_FALLBACK
#define PBGI_POINT_FALLBACK 1
#endif
#ifndef PBGI_LAMBDA
#define PBGI_LAMBDA 0.0
#endif
layout(std430, binding = PBGI_BIND_MICROBUFFER) buffer PbgiMicroBuffer { vec4 pbgi_mb[]; };
layout(std430, binding = PBGI_BIND_TEXELS) readonly buffer PbgiTexels { vec4 pbgi_texel[]; };
#ifdef PBGI_TEXEL_UBO
// the texel table again as a uniform block (walk.py binds it): on llvmpipe an SSBO load is a per-lane loop of
// bounds-checked scalar loads, a uniform-block load a branch-free gather
layout(std140) uniform PbgiTexelBlock { vec4 pbgi_texel_u[PBGI_TEXEL_UBO]; };
#define PBGI_TEXEL(i) pbgi_texel_u[i]
#else
#define PBGI_TEXEL(i) pbgi_texel[i]
#endif
// the receivers of the tile: (position.xyz, roughness) and (unit normal.xyz, metallic)
layout(std430, binding = PBGI_BIND_RECV_A) readonly buffer RecvA { vec4 recv_a[]; };
layout(std430, binding = PBGI_BIND_RECV_B) readonly buffer RecvB { vec4 recv_b[]; };
// the receivers' unit geometric normals (the surface's plane: the G-buffer's face normal; the shading normal where
// none is given), 0: the walk's near-field rule measures an object surfel's height above it, and Eq. 9 takes no
// light from directions on or below it
layout(std430, binding = PBGI_BIND_RECV_E) readonly buffer RecvE { vec4 recv_e[]; };

// Does the ray from the receiver along the unit direction w hit the node (every ray when ``inside`` the sphere;
// the disc of radius r and normal aloc from its front, in front of the receiver; else the sphere: w within the
// cone cos β about the centre direction c)? ``key``: its depth, the ray distance + PBGI_LAMBDA × the distance of
// the hit from the node's centre (pbgi_splat). vloc: the centre in the splat frame, va = vloc·aloc. Shared by the
// hemisphere and the lobe micro-buffers.
bool pbgi_ray_key(vec3 w, vec3 vloc, vec3 c, float dist, float r, vec3 aloc, float va, float cos_beta, bool inside,
                  bool disc, out float key) {
    key = dist;
    if (inside) return true;
    if (disc) {                                    // front side, in front of the receiver, within r
        float wa = dot(w, aloc);
        if (wa >= -1e-6) return false;
        float t = va / wa;
        if (t <= 0.0) return false;
        vec3 d = t * w - vloc;
        float d2 = dot(d, d);
        if (!(d2 <= r * r)) return false;
        key = t + PBGI_LAMBDA * sqrt(d2);
        return true;
    }
    float cw = dot(w, c);
    if (!(cw >= cos_beta)) return false;
    key = dist + PBGI_LAMBDA * dist * sqrt(max(1.0 - cw * cw, 0.0));
    return true;
}

// Depth of a sub-texel fallback splat: in [1e37, 2e37), increasing with dist, so a fallback only fills
// a texel that no node covers (any real hit, depth < 1e37, replaces it); among fallbacks the nearest wins.
// pbgi_depth_scale [m]: the scene's own length (walk.py sets the BSH root's radius; was an absolute 1 m, which
// lost the fallbacks' order in float32 past ~10³ m: docs/extremes.md).
uniform float pbgi_depth_scale;
float pbgi_fallback_depth(float dist) { return 1.0e37 * (1.0 + dist / (dist + pbgi_depth_scale)); }

void pbgi_splat_texel(uint idx, float dist, vec3 color) {
#ifdef PROF_NOWRITE
    if (dist < -1.0) pbgi_mb[idx] = vec4(color, dist);   // profiling: the texel tests without the buffer's traffic
#else
    if (dist < pbgi_mb[idx].w) pbgi_mb[idx] = vec4(color, dist);
#endif
}

// One node into the micro-buffer at `base`, as the sphere of radius r (disc = false; dist > r) or as
// the disc of radius r and normal aloc (disc = true). Every used texel whose ray hits it gets
// (color, key) if key < its stored depth; a node that hits no texel is splatted into the texel of its
// centre direction as a hole filler (PBGI_POINT_FALLBACK). Returns the loop iterations it ran (+1).
int pbgi_splat_node(uint base, int m, vec3 vloc, float dist, float r, vec3 aloc, bool disc, vec3 color) {
    bool inside = !disc && dist <= r;              // a sphere around the receiver: every used texel at depth
                                                   // dist, no fallback (pbgi_splat)
    vec3 c = vloc / dist;                          // unit direction to the centre (local frame)
    float s = min(r / dist, 1.0);
    float cos_beta = sqrt(max(1.0 - s * s, 0.0));  // ray hits sphere  <=>  dot(ω, c) ≥ cos β
    float chord = s * sqrt(2.0 / (1.0 + cos_beta)); // |ω − c| ≤ chord = 2 sin(β/2) inside the cone (no trig)
    // the texels whose square meets the disc |xy − c.xy| ≤ chord (a texel's representative direction lies
    // in its square, and |ω.xy − c.xy| ≤ |ω − c|): row by row, the disc's chord at the row's nearest y
    float R = chord * 1.00001 + 1e-6;
    float hm = 0.5 * float(m);
    ivec2 lo = inside ? ivec2(0) : pbgi_dir_texel(vec3(c.xy - R, 0.0), m);
    ivec2 hi = inside ? ivec2(m - 1) : pbgi_dir_texel(vec3(c.xy + R, 0.0), m);
    float va = dot(vloc, aloc);
    bool hit = false;
    int iters = 0;
    for (int v = lo.y; v <= hi.y; ++v) {
        float y0 = float(v) / hm - 1.0, y1 = float(v + 1) / hm - 1.0;
        float dy = max(0.0, max(y0 - c.y, c.y - y1));
        float hw = sqrt(max(R * R - dy * dy, 0.0));
        int u0 = inside ? 0 : max(lo.x, int(floor((c.x - hw + 1.0) * hm)));
        int u1 = inside ? m - 1 : min(hi.x, int(floor((c.x + hw + 1.0) * hm)));
        for (int u = u0; u <= u1; ++u) {
            int i = v * m + u;
            iters++;
            vec4 tx = PBGI_TEXEL(i);
#ifdef PROF_TEXEL_EMPTY
            hit = hit || tx.z > 7.0;               // profiling (bench_walk_profile.py): the loops without the tests
            continue;
#endif
            if (tx.z <= 0.0) continue;
            vec3 w = pbgi_xy_dir(tx.xy);
            float key;
            if (!pbgi_ray_key(w, vloc, c, dist, r, aloc, va, cos_beta, inside, disc, key)) continue;
            pbgi_splat_texel(base + uint(i), key, color);
            hit = true;
        }
    }
    if (PBGI_POINT_FALLBACK != 0 && !hit && !inside && c.z > 0.0 && (!disc || dot(c, aloc) < 0.0)) {   // sub-texel node
        ivec2 uv = pbgi_dir_texel(c, m);
        int i = uv.y * m + uv.x;
        if (PBGI_TEXEL(i).z > 0.0) pbgi_splat_texel(base + uint(i), pbgi_fallback_depth(dist), color);
    }
    return iters + 1;
}

int pbgi_splat(uint base, int m, vec3 vloc, float dist, float r, vec3 color) {
    return pbgi_splat_node(base, m, vloc, dist, r, vec3(0.0, 0.0, 1.0), false, color);
}

// Disc variant of pbgi_splat for nodes with a narrow normal cone (flat patches): the node is the disc of
// radius r through its centre, normal = the cone axis `aloc` (local frame). A texel's ray p + tω hits it
// if ω·a < 0 (front side), t = (v·a)/(ω·a) > 0 and |tω − v| ≤ r; key = t + PBGI_LAMBDA·|tω − v| (plane
// depth, as §5.2.1 approximates depth; among coplanar discs the one whose centre is nearest the hit).
// A sphere overstates a flat patch seen at a grazing angle (its cross-section does not shrink with the
// cosine); the disc does not. Same sub-texel fallback and return value as pbgi_splat.
int pbgi_splat_disc(uint base, int m, vec3 vloc, float dist, float r, vec3 aloc, vec3 color) {
    return pbgi_splat_node(base, m, vloc, dist, r, aloc, true, color);
}
// The radiance of hemisphere texel uv of the buffer at `base` with gaps filled as the lobe buffer's
// (pbgi_lobe_read): a texel whose depth is ≥ 1.25× that of at least 3/4 of its used neighbours (and of all
// but two) takes their mean radiance. (Experiment: the stop multiple below ~3.5 at m 32 leaked the sun through
// the grazing walls of the shipped scene's light shaft.)
vec3 pbgi_mb_read(uint base, int m, ivec2 uv) {
    vec4 c = pbgi_mb[base + uint(uv.y * m + uv.x)];
    int cnt = 0, nearer = 0;
    vec3 acc = vec3(0.0);
    for (int dv = -1; dv <= 1; ++dv) {
        for (int du = -1; du <= 1; ++du) {
            ivec2 q = uv + ivec2(du, dv);
            if ((du == 0 && dv == 0) || any(lessThan(q, ivec2(0))) || any(greaterThanEqual(q, ivec2(m)))) continue;
            int qi = q.y * m + q.x;
            if (pbgi_texel[qi].z <= 0.0) continue;
            vec4 o = pbgi_mb[base + uint(qi)];
            cnt++;
            if (1.25 * o.w < c.w && 6.0 * o.w > c.w) { nearer++; acc += o.rgb; }
        }
    }
    if (!(nearer > 0 && 4 * nearer >= 3 * cnt && nearer >= cnt - 2)) return c.rgb;
    acc /= float(nearer);
    return dot(c.rgb, vec3(1.0)) > 4.0 * dot(acc, vec3(1.0)) ? acc : c.rgb;
}
#endif  // PBGI_MICROBUFFER

// ---- The lobe micro-buffer (PBGI_LOBEBUFFER): a second, narrow micro-buffer per glossy receiver, centred on
// the mirror direction A = reflect(−ω_o, n) (the GGX lobe's centre), so a narrow lobe sees the room at its
// own resolution instead of the hemisphere's (a 24² hemisphere texel is ~5° at the pole and far wider at
// the rim; a roughness-0.1 lobe is a few degrees). Gnomonic projection in the lobe frame (U, V, A) =
// pbgi_frame(A): texel (u, v) of an ml×ml buffer has the direction normalize(T·x, T·y, 1), x, y the texel
// centre in [-1,1]² (pbgi_texel_xy); T = tan of the buffer's half-angle along U and V (per receiver,
// recv_c.w; 0 = no lobe buffer). Texel (u, v) of receiver k is pbgi_lobe[k·ml² + v·ml + u] = (R, G, B,
// depth), empty = (0, 0, 0, PBGI_FAR). Eq. 9 reads it for the VNDF samples that fall inside it.
#ifdef PBGI_LOBEBUFFER
layout(std430, binding = PBGI_BIND_LOBE) buffer PbgiLobe { vec4 pbgi_lobe[]; };

// The lobe axis [world, unit]: the mirror direction of the unit eye direction wo about the unit normal n.
vec3 pbgi_lobe_axis(vec3 n, vec3 wo) { return normalize(2.0 * dot(n, wo) * n - wo); }

vec3 pbgi_lobe_dir(ivec2 uv, int ml, float T) { return normalize(vec3(pbgi_texel_xy(uv, ml) * T, 1.0)); }

// The lobe texel holding the lobe-frame direction l (false when l is outside the buffer).
bool pbgi_lobe_texel(vec3 l, int ml, float T, out ivec2 uv) {
    uv = ivec2(0);
    if (!(l.z > 0.0)) return false;
    vec2 g = l.xy / (l.z * T);
    if (!(abs(g.x) < 1.0 && abs(g.y) < 1.0)) return false;
    uv = clamp(ivec2(floor((g + 1.0) * 0.5 * float(ml))), ivec2(0), ivec2(ml - 1));
    return true;
}

// The lobe buffer's half-angle tangent actually used by a receiver: T (from cover·α), widened so that a lobe
// texel is no finer than `leaf_r` (the cloud's median leaf splat radius [m]) seen at the depth d that the
// receiver's hemisphere buffer holds along the axis (axis_local: the axis in the receiver's (t, b, n) frame),
// T ≥ leaf_r·ml / (2d): finer texels see between the leaves' discs (they cover ~2× their points' area) into
// what lies behind. At most t_max (≈ 68°: a wider buffer is the hemisphere's job). The walk and Eq. 9 both
// call it on the same finished hemisphere buffer, so they agree.
float pbgi_lobe_tan(float T, uint hbase, int m, int ml, vec3 axis_local, float leaf_r, float t_max) {
    if (!(T > 0.0) || !(leaf_r > 0.0)) return T;
    ivec2 uv = pbgi_dir_texel(axis_local, m);
    float d = pbgi_mb[hbase + uint(uv.y * m + uv.x)].w;
    if (!(d < 1.0e37)) return T;                   // nothing (or only sub-texel fillers) along the axis
    return min(max(T, leaf_r * float(ml) / (2.0 * d)), t_max);
}

void pbgi_lobe_splat_texel(uint idx, float key, vec3 color) {
    if (key < pbgi_lobe[idx].w) pbgi_lobe[idx] = vec4(color, key);
}

// One node into the lobe buffer at `base` (vloc, aloc in the lobe frame): the same ray tests, depth keys
// and sub-texel fallback as pbgi_splat_node. The texel range: a direction within β = asin(r/dist) of the
// centre direction c (polar angle θ from A) lies within β / cos²(θ + β) of c's gnomonic point (the
// gnomonic map stretches arcs by at most 1/cos² of their polar angle); past θ + β ≥ 1.4 rad, every texel.
int pbgi_splat_lobe(uint base, int ml, float T, vec3 vloc, float dist, float r, vec3 aloc, bool disc, vec3 color) {
    bool inside = !disc && dist <= r;
    vec3 c = vloc / dist;
    float s = min(r / dist, 1.0);
    float cos_beta = sqrt(max(1.0 - s * s, 0.0));
    ivec2 lo = ivec2(0), hi = ivec2(ml - 1);
    vec2 gn = vec2(0.0);                           // c's gnomonic point and the bound, in texel-grid units [-1, 1]
    float Rn = 1.0e30;
    float hm = 0.5 * float(ml);
    if (!inside) {
        float beta = asin(s);
        float th = acos(clamp(c.z, -1.0, 1.0));
        if (th + beta < 1.4) {
            float ct = cos(th + beta);
            Rn = (beta / (ct * ct)) / T * 1.00001 + 1e-6;
            gn = c.xy / (c.z * T);
            lo = max(ivec2(floor((gn - Rn + 1.0) * hm)), ivec2(0));
            hi = min(ivec2(floor((gn + Rn + 1.0) * hm)), ivec2(ml - 1));
        }
    }
    float va = dot(vloc, aloc);
    bool hit = false;
    int iters = 0;
    for (int v = lo.y; v <= hi.y; ++v) {
        int u0 = lo.x, u1 = hi.x;
        if (Rn < 1.0e29) {                         // only the texels whose square meets the bound's disc
            float y0 = float(v) / hm - 1.0, y1 = float(v + 1) / hm - 1.0;
            float dy = max(0.0, max(y0 - gn.y, gn.y - y1));
            float hw = sqrt(max(Rn * Rn - dy * dy, 0.0));
            u0 = max(u0, int(floor((gn.x - hw + 1.0) * hm)));
            u1 = min(u1, int(floor((gn.x + hw + 1.0) * hm)));
        }
        for (int u = u0; u <= u1; ++u) {
            iters++;
            vec3 w = pbgi_lobe_dir(ivec2(u, v), ml, T);
            float key;
            if (!pbgi_ray_key(w, vloc, c, dist, r, aloc, va, cos_beta, inside, disc, key)) continue;
            pbgi_lobe_splat_texel(base + uint(v * ml + u), key, color);
            hit = true;
        }
    }
    ivec2 uv;
    if (PBGI_POINT_FALLBACK != 0 && !hit && !inside && (!disc || dot(c, aloc) < 0.0) && pbgi_lobe_texel(c, ml, T, uv))
        pbgi_lobe_splat_texel(base + uint(uv.y * ml + uv.x), pbgi_fallback_depth(dist), color);
    return iters + 1;
}

// The radiance of lobe texel uv of the buffer at `base`, holes filled: at the lobe's fine texels the walk reaches
// the leaves, whose discs cover ~2× their points' area and so leave ~10 % of a randomly sampled surface
// uncovered (1 − e⁻²), and a texel ray through such a gap sees what lies behind the wall (measured: the sun
// through a wall, 10⁴× the image). A texel whose depth is ≥ 1.25× that of at least 3/4 of its neighbours (and
// of all but two) is taken for a gap: it gets the mean radiance of those nearer neighbours. A real opening
// (a window, a silhouette) is wider than two texels, so most of its texels have far neighbours and stay.
vec3 pbgi_lobe_read(uint base, int ml, ivec2 uv) {
    vec4 c = pbgi_lobe[base + uint(uv.y * ml + uv.x)];
    int cnt = 0, nearer = 0;
    vec3 acc = vec3(0.0);
    for (int dv = -1; dv <= 1; ++dv) {
        for (int du = -1; du <= 1; ++du) {
            ivec2 q = uv + ivec2(du, dv);
            if ((du == 0 && dv == 0) || any(lessThan(q, ivec2(0))) || any(greaterThanEqual(q, ivec2(ml)))) continue;
            vec4 o = pbgi_lobe[base + uint(q.y * ml + q.x)];
            cnt++;
            if (1.25 * o.w < c.w) { nearer++; acc += o.rgb; }
        }
    }
    return (nearer > 0 && 4 * nearer >= 3 * cnt && nearer >= cnt - 2) ? acc / float(nearer) : c.rgb;
}
#ifdef PBGI_MICROBUFFER
// Does the lobe texel (depth key `lobe_depth`) see through a surface that the receiver's hemisphere buffer (at
// `hbase`, side m) holds all around the same direction (hemisphere texel `uv`)? True when the lobe depth is more
// than 1.25× the depth of every used hemisphere texel of the 3×3 around uv. The lobe walk reaches the leaves
// (pbgi_lobe_tan: texels of one leaf radius), whose discs leave ~13 % of a randomly sampled surface open
// (1 − e⁻²), and a cluster of such gaps is too wide for pbgi_lobe_read's fill; the hemisphere walk stops at
// nodes several times larger, which close them. A real opening as wide as a hemisphere texel shows in one of the
// nine (at m 24: ~5°, 1 m at 12 m), so only a smaller one loses its lobe-resolution view (Eq. 9 then reads the
// hemisphere buffer there); a thin occluder against an empty background (nine texels not all near) is not caught.
// Issue 22d: a 2–3-texel gap in the bowl room's roof beams, 11.5 m away, showed the sun (10⁵× the room) to one
// or two VNDF samples of 1024 (150–300 against 0.2–2.4 on the bowl's rim; a ray cast on the meshes meets the
// beams there).
bool pbgi_lobe_sees_through(uint hbase, int m, ivec2 uv, float lobe_depth) {
    if (!(lobe_depth > 1.25 * pbgi_mb[hbase + uint(uv.y * m + uv.x)].w)) return false;
    for (int dv = -1; dv <= 1; ++dv) {
        for (int du = -1; du <= 1; ++du) {
            ivec2 q = uv + ivec2(du, dv);
            if (any(lessThan(q, ivec2(0))) || any(greaterThanEqual(q, ivec2(m)))) continue;
            int qi = q.y * m + q.x;
            if (pbgi_texel[qi].z <= 0.0) continue;
            if (!(lobe_depth > 1.25 * pbgi_mb[hbase + uint(qi)].w)) return false;
        }
    }
    return true;
}
#endif
#endif  // PBGI_LOBEBUFFER

#endif  // PBGI_COMMON_GLSL
