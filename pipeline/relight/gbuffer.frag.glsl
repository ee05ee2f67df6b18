#version 430
// G-buffer fragment stage: float32 targets
//   0: world position (xyz) + coverage 1     1: unit shading normal (xyz), 0
//   2: base colour (linear rgb) + metallic   3: roughness, emission (linear rgb radiance)
//   4: unit geometric normal (xyz), 0 — the face's plane (from the screen-space derivatives of the position),
//      turned towards the eye; the shading normal where that is degenerate. Eq. 9 takes no light from below it
//      (pbgi_common.glsl pbgi_geom_local): a smooth shading normal tilts past the face at silhouettes.
// The shading normal is the interpolated vertex normal; where that is missing, zero or not finite
// (degenerate triangles, bad files) the geometric normal from screen-space derivatives is used, and
// if that is degenerate too, the direction to the eye. Back faces (double-sided materials only;
// single-sided ones are culled) get the flipped normal. Colours: factor × texture × vertex colour; emission:
// factor (× KHR_materials_emissive_strength) × emissive texture. Each texture is looked up at its own
// KHR_texture_transform of the UVs (bc_xf, mr_xf, em_xf, nm_xf: 3×3 affine, identity when the file has none).
// A glTF normal map (tangent space, +X right, +Y up the texture, linear; xy × its scale) perturbs the shading
// normal in the frame of the screen-space derivatives of position and UV (a per-pixel cotangent frame: the
// file's TANGENT attribute is not read).
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
uniform int has_em_tex;
uniform int has_nm_tex;
uniform float nm_scale;
uniform mat3 nm_xf;
uniform vec3 emissive;
uniform mat3 bc_xf;
uniform mat3 mr_xf;
uniform mat3 em_xf;
uniform sampler2D bc_tex;
uniform sampler2D mr_tex;
uniform sampler2D em_tex;
uniform sampler2D nm_tex;
layout(location = 0) out vec4 o_pos;
layout(location = 1) out vec4 o_nrm;
layout(location = 2) out vec4 o_mat;
layout(location = 3) out vec4 o_rgh;
layout(location = 4) out vec4 o_geo;

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
    if (has_nm_tex != 0) {
        vec2 uvn = (nm_xf * vec3(v_uv, 1.0)).xy;
        vec3 dp1 = dFdx(v_pos), dp2 = dFdy(v_pos);
        vec2 du1 = dFdx(uvn), du2 = dFdy(uvn);
        vec3 p2 = cross(dp2, n), p1 = cross(n, dp1);
        vec3 T = p2 * du1.x + p1 * du2.x, B = p2 * du1.y + p1 * du2.y;
        float m = max(dot(T, T), dot(B, B));
        if (m > 0.0 && !isinf(m) && !isnan(m)) {
            vec3 tn = texture(nm_tex, uvn).xyz * 2.0 - 1.0;
            tn.xy *= nm_scale;
            vec3 np = mat3(T * inversesqrt(m), B * inversesqrt(m), n) * tn;
            if (!bad(np)) n = normalize(np);
        }
    }
    vec3 bc = base_color * v_col;
    float met = metallic, rgh = roughness;
    if (has_bc_tex != 0) bc *= texture(bc_tex, (bc_xf * vec3(v_uv, 1.0)).xy).rgb;
    if (has_mr_tex != 0) { vec3 mr = texture(mr_tex, (mr_xf * vec3(v_uv, 1.0)).xy).rgb; rgh *= mr.g; met *= mr.b; }
    vec3 em = emissive;
    if (has_em_tex != 0) em *= texture(em_tex, (em_xf * vec3(v_uv, 1.0)).xy).rgb;
    o_pos = vec4(v_pos, 1.0);
    o_nrm = vec4(n, 0.0);
    o_mat = vec4(bc, clamp(met, 0.0, 1.0));
    o_rgh = vec4(clamp(rgh, 0.0, 1.0), max(em, vec3(0.0)));
    o_geo = vec4(!bad(ng) ? ng : n, 0.0);
}
