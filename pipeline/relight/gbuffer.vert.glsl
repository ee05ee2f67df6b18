#version 430
// G-buffer vertex stage: positions and normals are already in world space (metres).
uniform mat4 view_proj;
in vec3 in_pos;
in vec3 in_nrm;
in vec2 in_uv;
in vec3 in_col;
out vec3 v_pos;
out vec3 v_nrm;
out vec2 v_uv;
out vec3 v_col;
void main() {
    v_pos = in_pos;
    v_nrm = in_nrm;
    v_uv = in_uv;
    v_col = in_col;
    gl_Position = view_proj * vec4(in_pos, 1.0);
}
