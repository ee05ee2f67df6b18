#version 430
// Emits k points per input point: value = 10·input + i (checks GS + transform feedback).
layout(points) in;
layout(points, max_vertices = 16) out;
in float v_val[];
out float out_val;
uniform int k;
void main() {
    for (int i = 0; i < k; ++i) {
        out_val = v_val[0] * 10.0 + float(i);
        EmitVertex();
        EndPrimitive();
    }
}
