#version 430
// gaussians.vert.glsl — one 3D Gaussian splat (Kerbl et al. 2023) as one point sprite, drawn back to front. The
// projection is gaussians.py's _projected (its twin in float64): the 3D covariance Σ = R S Sᵀ Rᵀ (R from the unit
// quaternion, S = diag σ) in camera space, projected with the perspective's Jacobian J (the EWA splat Σ' = J Σ Jᵀ +
// 0.3 px² of low-pass, as the reference rasteriser); the sprite 2·3√λ_max pixels wide (≤ 255: llvmpipe's largest
// point; a wider splat is cut at its sprite's edge and counted by gaussians.py) around the projected centre.
// Camera: OpenGL eye space (looking down −z), focal length f [pixels], principal point at the image centre; window
// y grows with camera +y; the framebuffer has a guard band of `margin` pixels (a sprite whose centre is outside
// the image still reaches it: GL clips points by their centre).
in vec3 in_pos;          // centre [m]
in vec3 in_sigma;        // standard deviations along the splat's axes [m]
in vec4 in_quat;         // unit quaternion (w, x, y, z): splat axes → world
in float in_opacity;     // [0, 1]
in vec3 in_color;        // linear RGB (any range: HDR)
uniform mat3 R;          // world → camera rotation
uniform vec3 eye;        // [m]
uniform float f;         // focal length [pixels]
uniform vec2 size;       // W, H of the image [pixels]
uniform float margin;    // guard band [pixels]
uniform float near;      // [m]
flat out vec2 v_uv;      // the projected centre in framebuffer pixels
flat out vec3 v_conic;   // Σ'⁻¹ as (a, b, c): [[a, b], [b, c]] [px⁻²]
flat out float v_rad;    // 3 √λ_max [px]
flat out float v_opacity;
flat out vec3 v_color;

mat3 quat_matrix(vec4 q) {
    float w = q.x, x = q.y, y = q.z, z = q.w;
    return mat3(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y),     // column 0
                2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x),     // column 1
                2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y));    // column 2
}

void main() {
    vec3 c = R * (in_pos - eye);
    float d = -c.z;
    v_opacity = in_opacity;
    v_color = in_color;
    v_conic = vec3(0.0);
    v_rad = 0.0;
    v_uv = vec2(-1e9);
    gl_PointSize = 1.0;
    if (d <= near) { gl_Position = vec4(0.0, 0.0, 2.0, 1.0); return; }   // clipped
    mat3 M = R * quat_matrix(in_quat) * mat3(in_sigma.x, 0.0, 0.0, 0.0, in_sigma.y, 0.0, 0.0, 0.0, in_sigma.z);
    // (u, v) = f (x, y) / d + size / 2, d = −z: ∂(u, v)/∂(x, y, z) rows (f/d, 0, f x/d²), (0, f/d, f y/d²)
    mat3x2 J = mat3x2(f / d, 0.0, 0.0, f / d, f * c.x / (d * d), f * c.y / (d * d));
    mat3x2 JM = J * M;
    mat2 P = JM * transpose(JM) + mat2(0.3, 0.0, 0.0, 0.3);
    float det = P[0][0] * P[1][1] - P[0][1] * P[0][1];
    if (!(det > 0.0)) { gl_Position = vec4(0.0, 0.0, 2.0, 1.0); return; }
    v_conic = vec3(P[1][1], -P[0][1], P[0][0]) / det;
    float mid = 0.5 * (P[0][0] + P[1][1]);
    v_rad = 3.0 * sqrt(mid + sqrt(max(mid * mid - det, 0.1)));
    v_uv = f * c.xy / d + 0.5 * size + margin;
    vec2 full = size + 2.0 * margin;
    gl_Position = vec4(v_uv / full * 2.0 - 1.0, 0.0, 1.0);
    gl_PointSize = min(2.0 * v_rad + 1.0, 255.0);
}
