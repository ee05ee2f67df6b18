// brdf.glsl — the BRDFs of pipeline/gather/brdf.py in GLSL (same formulas, same conventions; see its docstring).
// wi: towards the light, wo: towards the viewer, n: shading normal (all unit). Returns f(wi, wo) [1/sr],
// linear RGB, zero when wi or wo is below the surface.
//   BRDF_LAMBERT: base/π.
//   BRDF_GGX:     GGX D with α = roughness², Schlick F with F0 = mix(0.04, base, metallic), Smith masking
//                 height-correlated (masking = MASK_HEIGHT_CORRELATED) or separable G1·G1
//                 (MASK_SEPARABLE, Mitsuba's roughconductor); plus (1 − metallic)·base/π.
//   BRDF_DISNEY:  Burley 2012 principled, glTF metallic-roughness mapping (specular 0.5, no sheen,
//                 clearcoat, subsurface): Fd90 diffuse × (1 − metallic) + GTR2 specular, separable Smith
//                 with α_g = (0.5 + roughness/2)².
#ifndef PCRELIGHT_BRDF_GLSL
#define PCRELIGHT_BRDF_GLSL

#define BRDF_LAMBERT 0
#define BRDF_GGX 1
#define BRDF_DISNEY 2
#define MASK_HEIGHT_CORRELATED 0
#define MASK_SEPARABLE 1
#define BRDF_PI 3.14159265358979323846
#define BRDF_ALPHA_MIN 1e-4

vec3 brdf_f0(vec3 base, float metallic) { return mix(vec3(0.04), base, metallic); }

vec3 brdf_fresnel_schlick(vec3 f0, float c) {
    float k = 1.0 - clamp(c, 0.0, 1.0);
    float k2 = k * k;
    return f0 + (1.0 - f0) * (k2 * k2 * k);
}

float brdf_ggx_d(float nh, float alpha) {
    if (nh <= 0.0) return 0.0;
    float a2 = alpha * alpha;
    float t = nh * nh * (a2 - 1.0) + 1.0;
    return a2 / (float(BRDF_PI) * t * t);
}

float brdf_smith_g1(float c, float alpha) {
    c = clamp(c, 0.0, 1.0);
    float a2 = alpha * alpha;
    return 2.0 * c / max(c + sqrt(a2 + (1.0 - a2) * c * c), 1e-30);
}

float brdf_smith_lambda(float c, float alpha) {
    c = clamp(c, 1e-12, 1.0);
    float c2 = c * c;
    return 0.5 * (sqrt(1.0 + alpha * alpha * (1.0 - c2) / c2) - 1.0);
}

float brdf_smith_g2_hc(float nl, float nv, float alpha) {
    return 1.0 / (1.0 + brdf_smith_lambda(nl, alpha) + brdf_smith_lambda(nv, alpha));
}

// Diffuse and specular parts separately (brdf_eval = their sum). Both zero below the surface.
vec3 brdf_diffuse(int kind, vec3 wi, vec3 wo, vec3 n, vec3 base, float metallic, float roughness) {
    float nl = dot(wi, n), nv = dot(wo, n);
    if (nl <= 0.0 || nv <= 0.0) return vec3(0.0);
    if (kind == BRDF_LAMBERT) return base / float(BRDF_PI);
    if (kind == BRDF_GGX) return (1.0 - metallic) * base / float(BRDF_PI);
    vec3 h = normalize(wi + wo);
    float lh = dot(wi, h);
    float fl = pow(1.0 - clamp(nl, 0.0, 1.0), 5.0);
    float fv = pow(1.0 - clamp(nv, 0.0, 1.0), 5.0);
    float fd90 = 0.5 + 2.0 * roughness * lh * lh;
    return (1.0 - metallic) * base / float(BRDF_PI) * (1.0 + (fd90 - 1.0) * fl) * (1.0 + (fd90 - 1.0) * fv);
}

// F·G for the specular lobe (shared by the evaluation and the VNDF-sampling weight).
vec3 brdf_spec_fg(int kind, int masking, float nl, float nv, float lh, vec3 base, float metallic, float roughness,
                  float alpha) {
    vec3 f = brdf_fresnel_schlick(brdf_f0(base, metallic), lh);
    float g;
    if (kind == BRDF_GGX)
        g = masking == MASK_SEPARABLE ? brdf_smith_g1(nl, alpha) * brdf_smith_g1(nv, alpha) : brdf_smith_g2_hc(nl, nv, alpha);
    else {
        float ag = (0.5 + 0.5 * roughness) * (0.5 + 0.5 * roughness);
        g = brdf_smith_g1(nl, ag) * brdf_smith_g1(nv, ag);
    }
    return f * g;
}

vec3 brdf_specular(int kind, int masking, vec3 wi, vec3 wo, vec3 n, vec3 base, float metallic, float roughness) {
    float nl = dot(wi, n), nv = dot(wo, n);
    if (kind == BRDF_LAMBERT || nl <= 0.0 || nv <= 0.0) return vec3(0.0);
    vec3 h = wi + wo;
    float hl = length(h);
    h = hl > 0.0 ? h / hl : n;
    float alpha = max(roughness * roughness, float(BRDF_ALPHA_MIN));
    float d = brdf_ggx_d(dot(n, h), alpha);
    return brdf_spec_fg(kind, masking, nl, nv, dot(wi, h), base, metallic, roughness, alpha) * (d / max(4.0 * nl * nv, 1e-30));
}

vec3 brdf_eval(int kind, int masking, vec3 wi, vec3 wo, vec3 n, vec3 base, float metallic, float roughness) {
    return brdf_diffuse(kind, wi, wo, n, base, metallic, roughness)
         + brdf_specular(kind, masking, wi, wo, n, base, metallic, roughness);
}

// Heitz 2018 visible-normal sampling of GGX (local frame, n = +z, wo.z > 0); u in [0,1)².
// Returns wi (may be below the horizon). The estimator of ∫ f_spec (n·wi) L dwi is
// L(wi) · brdf_spec_fg(...) / G1(wo, α) with pdf = G1(wo) D(h) / (4 wo.z).
vec3 brdf_sample_vndf(vec3 wo, float alpha, vec2 u) {
    vec3 vh = normalize(vec3(alpha * wo.x, alpha * wo.y, wo.z));
    float lensq = vh.x * vh.x + vh.y * vh.y;
    vec3 t1 = lensq > 0.0 ? vec3(-vh.y, vh.x, 0.0) / sqrt(lensq) : vec3(1.0, 0.0, 0.0);
    vec3 t2 = cross(vh, t1);
    float r = sqrt(u.x);
    float phi = 2.0 * float(BRDF_PI) * u.y;
    float p1 = r * cos(phi), p2 = r * sin(phi);
    float s = 0.5 * (1.0 + vh.z);
    p2 = (1.0 - s) * sqrt(max(1.0 - p1 * p1, 0.0)) + s * p2;
    vec3 nh = p1 * t1 + p2 * t2 + sqrt(max(0.0, 1.0 - p1 * p1 - p2 * p2)) * vh;
    vec3 h = normalize(vec3(alpha * nh.x, alpha * nh.y, max(0.0, nh.z)));
    return reflect(-wo, h);
}

#endif  // PCRELIGHT_BRDF_GLSL
