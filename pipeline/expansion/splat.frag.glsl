#version 430
flat in float v_d;
flat in float v_rp;
flat in float v_radius;
flat in vec2 v_uv;
flat in int v_id;
uniform float margin;
uniform float far;       // depth normalisation: gl_FragDepth = sphere depth / far
layout(location = 0) out int out_id;
layout(location = 1) out float out_d;
void main() {
    vec2 pix = gl_FragCoord.xy - vec2(margin);        // this pixel's centre in face pixels (i + 0.5)
    vec2 dd = pix - v_uv;
    float rho2 = dot(dd, dd) / max(v_rp * v_rp, 1e-30);
    bool centre = all(equal(floor(pix), floor(v_uv)));
    if (rho2 > 1.0 && !centre) discard;
    float ze = v_d - v_radius * sqrt(max(0.0, 1.0 - rho2));
    gl_FragDepth = clamp(ze / far, 0.0, 1.0);
    out_id = v_id;
    out_d = v_d;
}
