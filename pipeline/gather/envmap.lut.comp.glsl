#version 430
// envmap.lut.comp.glsl — the split sum's second factor (Karis 2013) for brdf.glsl's BRDF `brdf_kind`, per
// (n·v, roughness) on the grid (x, y)/(size − 1) (n·v ≥ 1e-3; the shader reads texel centres there): R = A (scale of F0), G = B (bias) of
// ∫ f_spec (n·l) dl = F0·A + B (Schlick F is affine in F0: A = the integral at F0 = 1 minus that at F0 = 0),
// by `samples` Hammersley visible-normal samples (brdf_sample_vndf, weight brdf_spec_fg / G1(v), as
// eq9.comp.glsl's lobe sampling); B = C: ∫ brdf_diffuse (n·l) dl at base colour 1, metallic 0, by
// cosine-weighted samples (1 for Lambert and GGX's Lambert part; Burley's retro-reflection for Disney).
#include "brdf.glsl"

layout(local_size_x = 8, local_size_y = 8) in;
layout(rgba32f, binding = PBGI_BIND_IMAGE_OUT) writeonly uniform image2D lut;
uniform int size;
uniform int samples;
uniform int brdf_kind;
uniform int masking;

vec2 envmap_hammersley(uint i, uint n) {
    uint b = bitfieldReverse(i);
    return vec2((float(i) + 0.5) / float(n), float(b) * 2.3283064365386963e-10);
}

void main() {
    ivec2 g = ivec2(gl_GlobalInvocationID.xy);
    if (g.x >= size || g.y >= size) return;
    float nv = max(float(g.x) / float(size - 1), 1e-3);
    float rough = float(g.y) / float(size - 1);
    float alpha = max(rough * rough, float(BRDF_ALPHA_MIN));
    vec3 wo = vec3(sqrt(max(1.0 - nv * nv, 0.0)), 0.0, nv);
    const vec3 z = vec3(0.0, 0.0, 1.0);
    float a = 0.0, b = 0.0, c = 0.0;
    float g1o = max(brdf_smith_g1(nv, alpha), 1e-30);
    for (int i = 0; i < samples; ++i) {
        vec2 u = envmap_hammersley(uint(i), uint(samples));
        if (brdf_kind != BRDF_LAMBERT) {
            vec3 wi = brdf_sample_vndf(wo, alpha, u);
            if (wi.z > 0.0) {
                vec3 h = normalize(wi + wo);
                float one = brdf_spec_fg(brdf_kind, masking, wi.z, nv, dot(wi, h), vec3(1.0), 1.0, rough, alpha).x;
                float zero = brdf_spec_fg(brdf_kind, masking, wi.z, nv, dot(wi, h), vec3(0.0), 1.0, rough, alpha).x;
                a += (one - zero) / g1o;
                b += zero / g1o;
            }
        }
        float r = sqrt(u.x), phi = 2.0 * float(BRDF_PI) * u.y;
        vec3 wc = vec3(r * cos(phi), r * sin(phi), sqrt(max(1.0 - u.x, 0.0)));
        c += brdf_diffuse(brdf_kind, wc, wo, z, vec3(1.0), 0.0, rough).x * float(BRDF_PI);
    }
    float inv = 1.0 / float(samples);
    imageStore(lut, g, vec4(a * inv, b * inv, c * inv, 1.0));
}
