#version 430
// envmap.shade.comp.glsl — image-based lighting of the receivers from one environment (papers 002, 004):
//   L_out = kd/π · E(n) · C(n·v, r)  +  Lpre(R, r) · (F0·A(n·v, r) + B(n·v, r))
// E: the irradiance map (lat-long, +Y up, bilinear; envmap.py `irradiance_latlong`); Lpre: the prefiltered
// radiance cube read at the lobe's dominant direction (the mirror direction R of v about n bent towards n as α
// grows: Lagarde & de Rousiers 2014, Frostbite), level roughness·max_lod (trilinear); A, B, C:
// envmap.lut.comp.glsl's table; kd = base colour (Lambert) or (1 − metallic)·base (GGX, Disney); F0 from
// brdf.glsl. Receiver buffers and `out` as eq9.comp.glsl's (bindings from bsh_format.GATHER_BINDINGS);
// a grazing or back-facing view is clamped to n·v = 1e-4 as there.
#include "brdf.glsl"

layout(local_size_x = 64) in;
layout(std430, binding = PBGI_BIND_RECV_A) readonly buffer RecvA { vec4 recv_a[]; };
layout(std430, binding = PBGI_BIND_RECV_B) readonly buffer RecvB { vec4 recv_b[]; };
layout(std430, binding = PBGI_BIND_RECV_C) readonly buffer RecvC { vec4 recv_c[]; };
layout(std430, binding = PBGI_BIND_RECV_D) readonly buffer RecvD { vec4 recv_d[]; };
layout(std430, binding = PBGI_BIND_OUT) writeonly buffer Out { vec4 out_rad[]; };

uniform sampler2D irr;      // irradiance E [W/m² up to the common scale], lat-long
uniform samplerCube pref;   // prefiltered radiance, level i = roughness i / max_lod
uniform sampler2D dfg;      // (A, B, C) over (n·v, roughness)
uniform float max_lod;
uniform int lut_size;       // dfg's side: entry (x, y) at n·v = x/(size − 1), roughness = y/(size − 1)
uniform int brdf_kind;
uniform uint n_recv;
uniform uint first;

vec2 envmap_latlong(vec3 d) {   // (φ + π) / 2π, θ / π with θ from +Y, φ = atan2(z, x)
    return vec2((atan(d.z, d.x) + float(BRDF_PI)) / (2.0 * float(BRDF_PI)), acos(clamp(d.y, -1.0, 1.0)) / float(BRDF_PI));
}

void main() {
    uint k = first + gl_GlobalInvocationID.x;
    if (k >= n_recv) return;
    vec3 n = normalize(recv_b[k].xyz);
    vec3 base = recv_c[k].rgb;
    float rough = recv_a[k].w, metal = recv_b[k].w;
    vec3 wo = recv_d[k].xyz;
    float nv = max(dot(n, wo), 1e-4);
    vec3 E = texture(irr, envmap_latlong(n)).rgb;
    vec3 acc;
    if (brdf_kind == BRDF_LAMBERT) {
        acc = base / float(BRDF_PI) * E;
    } else {
        vec3 t = texture(dfg, (vec2(nv, clamp(rough, 0.0, 1.0)) * float(lut_size - 1) + 0.5) / float(lut_size)).rgb;
        acc = (1.0 - metal) * base / float(BRDF_PI) * E * t.z;
        vec3 R = normalize(2.0 * dot(n, wo) * n - wo);
        float a = max(rough * rough, float(BRDF_ALPHA_MIN));
        R = normalize(mix(n, R, (1.0 - a) * (sqrt(1.0 - a) + a)));   // the lobe's dominant direction (Lagarde 2014)
        vec3 L = textureLod(pref, R, clamp(rough, 0.0, 1.0) * max_lod).rgb;
        acc += L * (brdf_f0(base, metal) * t.x + t.y);
    }
    out_rad[k] = vec4(acc, 1.0);
}
