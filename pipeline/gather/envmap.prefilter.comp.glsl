#version 430
// envmap.prefilter.comp.glsl — one level of the prefiltered radiance cube map (split sum, Karis 2013):
// every texel direction N gets Σ L(l) (n·l) / Σ (n·l) over `samples` GGX samples of the half vector around
// N (v = n = N, α = max(roughness², BRDF_ALPHA_MIN)), each read from the mip-mapped source cube at the
// level whose texel solid angle matches the sample's share 1 / (samples · pdf(l)) (Colbert & Křivánek 2007,
// "PDF-based mip filtering"; +1 level as theirs). Half vectors come from brdf.glsl's visible-normal sampler
// with wo = n (= GGX D(h)(n·h) sampling), the density from its brdf_ggx_d: the BRDF code is shared.
// Texel (x, y) of face f: the OpenGL cube-map convention (s along x, t along y: GL spec Table 8.19), the
// layout of render-cubemaps' faces (pipeline/expansion/splats.py).
#include "brdf.glsl"

layout(local_size_x = 8, local_size_y = 8, local_size_z = 1) in;
layout(rgba32f, binding = PBGI_BIND_IMAGE_OUT) writeonly uniform imageCube dst;
uniform samplerCube src;
uniform int size;          // this level's face side [texels]
uniform float roughness;   // this level's roughness
uniform int samples;
uniform float src_omega;   // solid angle of a source level-0 texel, 4π / (6 S²) [sr]
uniform float src_max_lod;

vec3 envmap_cube_dir(int face, vec2 st) {
    vec2 c = st * 2.0 - 1.0;            // (sc, tc)
    if (face == 0) return vec3(1.0, -c.y, -c.x);
    if (face == 1) return vec3(-1.0, -c.y, c.x);
    if (face == 2) return vec3(c.x, 1.0, c.y);
    if (face == 3) return vec3(c.x, -1.0, -c.y);
    if (face == 4) return vec3(c.x, -c.y, 1.0);
    return vec3(-c.x, -c.y, -1.0);
}

vec2 envmap_hammersley(uint i, uint n) {
    uint b = bitfieldReverse(i);
    return vec2((float(i) + 0.5) / float(n), float(b) * 2.3283064365386963e-10);
}

void main() {
    ivec3 g = ivec3(gl_GlobalInvocationID);
    if (g.x >= size || g.y >= size) return;
    vec3 N = normalize(envmap_cube_dir(g.z, (vec2(g.xy) + 0.5) / float(size)));
    float alpha = max(roughness * roughness, float(BRDF_ALPHA_MIN));
    vec3 up = abs(N.y) < 0.999 ? vec3(0.0, 1.0, 0.0) : vec3(1.0, 0.0, 0.0);
    vec3 T = normalize(cross(up, N));
    vec3 B = cross(N, T);
    const vec3 z = vec3(0.0, 0.0, 1.0);
    vec3 acc = vec3(0.0);
    float wsum = 0.0;
    for (int i = 0; i < samples; ++i) {
        vec2 u = samples == 1 ? vec2(0.0) : envmap_hammersley(uint(i), uint(samples));
        vec3 l = brdf_sample_vndf(z, alpha, u);
        if (l.z <= 0.0) continue;
        vec3 h = normalize(l + z);
        float pdf = brdf_ggx_d(h.z, alpha) * 0.25;            // D(h)(n·h) / (4 v·h), v = n
        float lod = src_max_lod;
        if (pdf > 0.0) lod = clamp(0.5 * log2(1.0 / (float(samples) * pdf * src_omega)) + 1.0, 0.0, src_max_lod);
        if (samples == 1) lod = 0.0;
        vec3 L = T * l.x + B * l.y + N * l.z;
        acc += textureLod(src, L, lod).rgb * l.z;
        wsum += l.z;
    }
    imageStore(dst, g, vec4(acc / max(wsum, 1e-30), 1.0));
}
