#version 430
// eq9.comp.glsl — final gather (Eq. 9): L_out(ω_o) = Σ_ij f(ω_ij, ω_o) C_ij Ω_ij (n·ω_ij), with
// Ω_ij (n·ω_ij) = the texel table's `proj` (exact ∫cos dω per texel, or Eq. 5's 2π/m²·cos for
// --solid-angle paper) and ω_ij its representative direction. Lambert skips the BRDF evaluation:
// L = base/π · Σ C_ij proj_ij. A specular lobe narrower than a couple of texels (α·m < lobe_texels)
// is integrated over the same piecewise-constant micro-buffer radiance by n×n stratified GGX
// visible-normal samples (Heitz 2018) instead of the texel sum (which under-resolves it); the
// diffuse part stays a texel sum. A sample inside the receiver's lobe buffer reads it, unless that texel lies > 1.25×
// deeper than all nine hemisphere texels around its direction (pbgi_lobe_sees_through: a gap between the lobe walk's
// leaves; the hemisphere buffer is read instead). Buffers (bindings from bsh_format.GATHER_BINDINGS): micro-buffers,
// texel table, recv_a (pos, roughness), recv_b (normal, metallic), recv_c (base colour, 0), recv_d (unit
// direction to the eye, 0), out (R, G, B, 1), emit (the emitters: isolated leaves that the walk does not
// splat, bsh.npz ``emitters``: centre + disc radius, unit normal + flat share c, radiance). An emitter is a
// point of an object smaller than the point spacing (a 4 cm lamp gets 2–3 points) or of a small bright
// object (a lamp of a few to twenty points): it stands for its share of the object's area, π r², and a
// closed object shows a quarter of its area from any side (Cauchy), so it adds
// f · L · π r² ((1 − c)/4 + c max(0, cos θ_e)) cos θ_r / (d² + r²): c = |Σ n| / n over its object's points
// (0 for an isolated point: two points of a sphere say nothing reliable about where it faces, and the disc
// model (cos θ_e) put 1.26× the truth on one view of the lamp room; ≈ 1 for a small flat patch, which
// shows its area once, to one side) — where the micro-buffer texel in its direction holds nothing
// nearer than d − max(r, 0.02 d) (a surface behind it, an empty texel or a hole filler). Splatted, a
// sub-texel disc lit a whole texel or none, so receivers caught a lamp or missed it (blotches).
// The geometric horizon: a texel, VNDF sample or emitter whose direction lies on or below the receiver's geometric
// plane (recv_e: the G-buffer's face normal; the shading normal where none is given) gives nothing — a path
// tracer's ray there meets the surface itself. A smooth shading normal tilts past the face at silhouettes, and its
// hemisphere then holds room light that the object blocks (its own near surfels are not splatted: walk.comp.glsl
// object_near). Where the two normals are equal nothing is tested (the images bit for bit as without it).
// Directions mode (n_views > 0; surfels.py's directional bounce): invocation g gathers receiver g / n_views towards
// the world direction view_dir[g % n_views] instead of its eye (zero below its tangent or geometric plane), into out[g]; the lobe
// buffers are not read (they are centred on the receiver's own mirror direction).
#define PBGI_NO_NODE_BUFFER
#define PBGI_MICROBUFFER
#define PBGI_LOBEBUFFER
#include "pbgi_common.glsl"
#include "brdf.glsl"

layout(local_size_x = 64) in;
layout(std430, binding = PBGI_BIND_RECV_C) readonly buffer RecvC { vec4 recv_c[]; };
layout(std430, binding = PBGI_BIND_RECV_D) readonly buffer RecvD { vec4 recv_d[]; };
layout(std430, binding = PBGI_BIND_OUT) writeonly buffer Out { vec4 out_rad[]; };
layout(std430, binding = PBGI_BIND_VIEW_DIRS) readonly buffer ViewDirs { vec4 view_dir[]; };
struct Emitter { vec4 pos_r; vec4 nrm; vec4 col; };
layout(std430, binding = PBGI_BIND_EMIT) readonly buffer Emit { Emitter emit[]; };

uniform uint n_recv;
uniform uint first;
uniform int m;
uniform int brdf_kind;
uniform int masking;
uniform int lobe_samples;   // n: n×n stratified VNDF samples for narrow specular lobes (0 = texel sum only)
uniform float lobe_texels;  // use lobe sampling when α·m < lobe_texels
uniform uint n_emit;        // emitters in `emit`
uniform int lobe_m;         // lobe micro-buffer side; a VNDF sample inside a receiver's lobe buffer (recv_c.w = T > 0)
                            // reads it instead of the hemisphere buffer
uniform float lobe_leaf_r;  // pbgi_lobe_tan (walk.comp.glsl)
uniform float lobe_tmax;
uniform uint n_views;       // directions mode: outgoing directions per receiver (0: towards recv_d, its eye)

// Eq. 9 at receiver k towards the unit world direction wo (the lobe buffer is read when use_lobe).
vec3 eq9_radiance(uint k, vec3 wo, bool use_lobe) {
    uint mm = uint(m * m);
    uint base = k * mm;
    vec3 n = recv_b[k].xyz;
    vec3 albedo = recv_c[k].rgb;
    vec3 acc = vec3(0.0);
    vec3 ng = recv_e[k].xyz;
    bool clip = any(notEqual(ng, n));      // the geometric horizon differs from the shading one
    vec3 t, b;
    pbgi_frame(n, t, b);
    vec3 gn = vec3(dot(ng, t), dot(ng, b), dot(ng, n));   // the geometric normal in the (t, b, n) frame
    if (brdf_kind == BRDF_LAMBERT) {
        for (uint i = 0u; i < mm; ++i) {
            vec4 tx = pbgi_texel[i];
            if (tx.w > 0.0 && !(clip && dot(pbgi_xy_dir(tx.xy), gn) <= 0.0))
                acc += pbgi_mb_read(base, m, ivec2(int(i) % m, int(i) / m)) * tx.w;
        }
        acc *= albedo / float(BRDF_PI);
    } else {
        vec3 wl = vec3(dot(wo, t), dot(wo, b), dot(wo, n));
        wl.z = max(wl.z, 1e-4);            // grazing / back-facing view: keep the lobe finite
        wl = normalize(wl);
        float rough = recv_a[k].w, metal = recv_b[k].w;
        float alpha = max(rough * rough, float(BRDF_ALPHA_MIN));
        // a lobe narrower than ~lobe_texels texels is integrated by VNDF sampling, else by the texel sum
        bool lobe = lobe_samples > 0 && alpha * float(m) < lobe_texels;
        const vec3 z = vec3(0.0, 0.0, 1.0);
        // a full metal under lobe sampling has no diffuse part (brdf_diffuse: (1 − metallic)·…): no texel sum
        for (uint i = 0u; i < ((lobe && metal >= 1.0) ? 0u : mm); ++i) {
            vec4 tx = pbgi_texel[i];
            if (tx.w <= 0.0) continue;
            vec3 c = pbgi_mb_read(base, m, ivec2(int(i) % m, int(i) / m));
            if (c == vec3(0.0)) continue;
            vec3 wi = pbgi_xy_dir(tx.xy);
            if (clip && dot(wi, gn) <= 0.0) continue;
            vec3 f = lobe ? brdf_diffuse(brdf_kind, wi, wl, z, albedo, metal, rough)
                          : brdf_eval(brdf_kind, masking, wi, wl, z, albedo, metal, rough);
            acc += f * c * tx.w;
        }
        if (lobe) {
            float g1o = brdf_smith_g1(wl.z, alpha);
            vec3 spec = vec3(0.0);
            float T = 0.0;
            vec3 lu = vec3(1.0, 0.0, 0.0), lv = vec3(0.0, 1.0, 0.0), la = z;    // the lobe frame in (t, b, n)
            vec3 fa = pbgi_lobe_axis(n, wo);               // the same axis, T and frame as walk.comp.glsl's
            if (use_lobe && lobe_m > 0)
                T = pbgi_lobe_tan(recv_c[k].w, base, m, lobe_m, vec3(dot(fa, t), dot(fa, b), dot(fa, n)), lobe_leaf_r,
                                  lobe_tmax);
            if (T > 0.0) {
                vec3 ut, vt;
                pbgi_frame(fa, ut, vt);
                lu = vec3(dot(ut, t), dot(ut, b), dot(ut, n));
                lv = vec3(dot(vt, t), dot(vt, b), dot(vt, n));
                la = vec3(dot(fa, t), dot(fa, b), dot(fa, n));
            }
            uint lbase = k * uint(lobe_m * lobe_m);
            for (int j = 0; j < lobe_samples * lobe_samples; ++j) {
                vec2 u = (vec2(j % lobe_samples, j / lobe_samples) + 0.5) / float(lobe_samples);
                vec3 wi = brdf_sample_vndf(wl, alpha, u);
                if (wi.z <= 0.0 || (clip && dot(wi, gn) <= 0.0)) continue;
                vec3 c;
                ivec2 luv;
                ivec2 uv = pbgi_dir_texel(wi, m);
                // the lobe texel, unless it sees through what the hemisphere buffer holds all around (a gap)
                if (T > 0.0 && pbgi_lobe_texel(vec3(dot(wi, lu), dot(wi, lv), dot(wi, la)), lobe_m, T, luv)
                    && !pbgi_lobe_sees_through(base, m, uv, pbgi_lobe[lbase + uint(luv.y * lobe_m + luv.x)].w)) {
                    c = pbgi_lobe_read(lbase, lobe_m, luv);
                } else {
                    uint ti = uint(uv.y * m + uv.x);
                    if (pbgi_texel[ti].z <= 0.0) continue;
                    c = pbgi_mb_read(base, m, uv);
                }
                vec3 h = normalize(wi + wl);
                spec += c * brdf_spec_fg(brdf_kind, masking, wi.z, wl.z, dot(wi, h), albedo, metal, rough, alpha);
            }
            acc += spec / (max(g1o, 1e-30) * float(lobe_samples * lobe_samples));
        }
    }
    if (n_emit > 0u) {
        vec3 p = recv_a[k].xyz;
        vec3 wl = normalize(vec3(dot(wo, t), dot(wo, b), max(dot(wo, n), 1e-4)));
        float rough = recv_a[k].w, metal = recv_b[k].w;
        const vec3 z = vec3(0.0, 0.0, 1.0);
        for (uint e = 0u; e < n_emit; ++e) {
            vec3 v = emit[e].pos_r.xyz - p;
            float d = length(v);
            if (!(d > 0.0)) continue;
            vec3 w = v / d;
            float cr = dot(w, n);
            if (cr <= 0.0 || (clip && dot(w, ng) <= 0.0)) continue;
            float r = emit[e].pos_r.w;
            vec3 wi = vec3(dot(w, t), dot(w, b), cr);
            ivec2 uv = pbgi_dir_texel(wi, m);
            if (pbgi_mb[base + uint(uv.y * m + uv.x)].w < d - max(r, 0.02 * d)) continue;   // occluded
            // its area seen: a quarter from any side for its closed part, cos θ_e one-sided for its flat share
            float c = emit[e].nrm.w;
            float seen = (1.0 - c) * 0.25 + c * max(0.0, -dot(emit[e].nrm.xyz, w));
            float proj = float(PBGI_PI) * r * r * seen * cr / (d * d + r * r);
            vec3 f = brdf_kind == BRDF_LAMBERT ? albedo / float(BRDF_PI)
                                               : brdf_eval(brdf_kind, masking, wi, wl, z, albedo, metal, rough);
            acc += f * emit[e].col.rgb * proj;
        }
    }
    return acc;
}

void main() {
    uint g = first + gl_GlobalInvocationID.x;
    uint nv = max(n_views, 1u);
    uint k = g / nv;
    if (k >= n_recv) return;
    vec3 wo = n_views == 0u ? recv_d[k].xyz : view_dir[g % nv].xyz;
    bool below = n_views > 0u && (dot(wo, recv_b[k].xyz) <= 0.0 || dot(wo, recv_e[k].xyz) <= 0.0);
    out_rad[g] = vec4(below ? vec3(0.0) : eq9_radiance(k, wo, n_views == 0u), 1.0);
}
