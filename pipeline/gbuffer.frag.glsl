#version 430
// G-buffer fragment stage: float32 targets
//   0: world position (xyz) + coverage 1     1: unit shading normal (xyz), 0
//   2: base colour (linear rgb) + metallic   3: roughness, 0, 0, 0
// The shading normal is the interpolated vertex normal; where that is missing, zero or not finite
// (degenerate triangles, bad files) the geometric normal from screen-space derivatives is used, and
// if that is degenerate too, the direction to the eye. Back faces (double-sided materials only;
// single-sided ones are culled) get the flipped normal. Colours: factor × texture × vertex colour.
in vec3 v_pos;
in vec3 v_nrm;
in vec2 v_uv;
in vec3 v_col;
uniform vec3 eye;
uniform vec3 base_color;
uniform float metallic;
uniform float roughness;
uniform int has_bc_tex;
uniform int has_mr_tex;
uniform sampler2D bc_tex;
uniform sampler2D mr_tex;
layout(location = 0) out vec4 o_pos;
layout(location = 1) out vec4 o_nrm;
layout(location = 2) out vec4 o_mat;
layout(location = 3) out vec4 o_rgh;

bool bad(vec3 v) { return any(isnan(v)) || any(isinf(v)) || dot(v, v) < 1e-30; }

void main() {
    vec3 to_eye = eye - v_pos;
    vec3 ng = cross(dFdx(v_pos), dFdy(v_pos));
    if (!bad(ng)) { ng = normalize(ng); if (dot(ng, to_eye) < 0.0) ng = -ng; }
    vec3 n = v_nrm;
    if (!bad(n)) {
        n = normalize(n);
        if (!gl_FrontFacing) n = -n;
    } else {
        n = !bad(ng) ? ng : (!bad(to_eye) ? normalize(to_eye) : vec3(0.0, 1.0, 0.0));
    }
    vec3 bc = base_color * v_col;
    float met = metallic, rgh = roughness;
    if (has_bc_tex != 0) bc *= texture(bc_tex, v_uv).rgb;
    if (has_mr_tex != 0) { vec3 mr = texture(mr_tex, v_uv).rgb; rgh *= mr.g; met *= mr.b; }
    o_pos = vec4(v_pos, 1.0);
    o_nrm = vec4(n, 0.0);
    o_mat = vec4(bc, clamp(met, 0.0, 1.0));
    o_rgh = vec4(clamp(rgh, 0.0, 1.0), 0.0, 0.0, 0.0);
}
