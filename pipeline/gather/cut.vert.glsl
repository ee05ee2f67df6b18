#version 430
// cut.vert.glsl — pass-through of one (node, pixel) pair to the traversal geometry shader.
in uvec2 in_pair;      // (BSH node index, pixel code = level << 27 | Z-order index at that level)
out uvec2 v_pair;
void main() { v_pair = in_pair; }
