#version 430
// render-cubemaps (GL route): one point sprite per point into one cube-map face.
// Same rules as the numba splatter (render_cubemaps.py): disc of pixel radius f·r/d capped at
// max_px, the centre pixel always covered, sphere depth d − r·sqrt(1 − ρ²). Pixel (u, v) in face
// pixels (v grows with camera +Y = GL window y), drawn into a framebuffer with a guard band of
// `margin` pixels on every side so that sprites whose centre lies outside the face still reach it.
in vec3 in_pos;
in float in_radius;
uniform mat3 R;          // world → camera rotation
uniform vec3 eye;
uniform float f;         // focal length [pixels] (fx = fy, cx = W/2, cy = H/2)
uniform vec2 size;       // face W, H
uniform float margin;    // guard band [pixels] (≥ max_px + 1)
uniform float near;
uniform float max_px;
flat out float v_d;
flat out float v_rp;
flat out float v_radius;
flat out vec2 v_uv;
flat out int v_id;
void main() {
    vec3 c = R * (in_pos - eye);
    float d = -c.z;
    v_d = d;
    v_id = gl_VertexID;
    v_radius = in_radius;
    if (d <= near) {               // behind the near plane: not drawn
        gl_Position = vec4(0.0, 0.0, -2.0, 1.0);
        gl_PointSize = 1.0;
        v_rp = 0.0;
        v_uv = vec2(-1e9);
        return;
    }
    float rp = min(f * in_radius / d, max_px);
    vec2 uv = vec2(f * c.x / d, f * c.y / d) + 0.5 * size;
    v_rp = rp;
    v_uv = uv;
    vec2 full = size + 2.0 * margin;
    gl_Position = vec4((uv + margin) / full * 2.0 - 1.0, 0.0, 1.0);
    gl_PointSize = 2.0 * rp + 2.0;  // +2 px so the centre pixel is always rasterised; the fragment discards
}
