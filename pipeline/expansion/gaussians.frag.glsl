#version 430
// gaussians.frag.glsl — a splat's Gaussian at this pixel centre: α = min(0.99, opacity · exp(−½ dᵀ Σ'⁻¹ d)), dropped
// below 1/255 and outside ±3√λ_max (the reference rasteriser's rules; gaussians.py render_reference, its twin);
// premultiplied out (α·colour, α), blended "over" back to front (ONE, ONE_MINUS_SRC_ALPHA).
flat in vec2 v_uv;
flat in vec3 v_conic;
flat in float v_rad;
flat in float v_opacity;
flat in vec3 v_color;
layout(location = 0) out vec4 out_rgba;
void main() {
    vec2 d = gl_FragCoord.xy - v_uv;
    if (any(greaterThan(abs(d), vec2(v_rad)))) discard;
    float power = -0.5 * (v_conic.x * d.x * d.x + 2.0 * v_conic.y * d.x * d.y + v_conic.z * d.y * d.y);
    if (power > 0.0) discard;
    float a = min(0.99, v_opacity * exp(power));
    if (a < 1.0 / 255.0) discard;
    out_rgba = vec4(v_color * a, a);
}
