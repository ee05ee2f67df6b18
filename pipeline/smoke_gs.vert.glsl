#version 430
in float in_val;
out float v_val;
void main() { v_val = in_val; }
