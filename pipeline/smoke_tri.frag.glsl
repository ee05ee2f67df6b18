#version 430
out vec4 frag;
void main() { frag = vec4(1.0, 0.5, 0.25, 1.0); }
