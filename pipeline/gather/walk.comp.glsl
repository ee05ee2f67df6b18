#version 430
// walk.comp.glsl — fill one micro-buffer per receiver (§5.2): for every start node s of receiver k's CSR
// list (start_off[k] .. start_off[k+1]) run the stackless depth-first walk of s's sub-tree (visit i;
// descend to i+1 or jump to skip[i]), culling a node and its sub-tree by the horizon and Fig. 5
// back-face tests, splatting it when the stop rule Ω(A) ≤ stop_multiple·Ω_pix holds or it is a leaf.
// Classic = one start node, the root (use_lists = 0). Flat nodes (normal cone ≤ disc_cone) are splatted
// as discs (pbgi_splat_disc) at any distance, the others as spheres (pbgi_splat). (A flat cluster whose
// splat radius reached the receiver used to go to the sphere path, which fills every texel when the
// receiver is inside: a receiver above a pruned floor saw only floor — t_c 0.05 relit the sample at 0.22×.)
// Resumable: each dispatch runs at most `iter_budget` loop iterations per receiver (node visits +
// splat texels) and saves (start index, node, sub-tree end, visited) in `state`; receivers not finished
// bump `pending`, and the host dispatches again until pending == 0. Mesa llvmpipe silently stops loops
// after 65535 iterations per shader invocation (all SIMD lanes together), hence the budget.
// The micro-buffers are cleared by the host to (0, 0, 0, PBGI_FAR) before the first pass.
// Buffers (bindings from bsh_format.GATHER_BINDINGS): nodes, micro-buffers (vec4 R,G,B,depth per texel;
// receiver k at k·m²), texel table, recv_a (position.xyz, roughness), recv_b (normal.xyz, metallic),
// start_off (uint, P+1), start_node (uint), state (uvec4 per receiver), pending (uint counter), splat
// (float per node: the splat radius ≤ the node radius, bsh.npz splat_radius; the node radius stays the
// bound of the stop rule and the culls).
#define PBGI_MICROBUFFER
#include "pbgi_common.glsl"

layout(local_size_x = 64) in;
layout(std430, binding = PBGI_BIND_START_OFF) readonly buffer StartOff { uint start_off[]; };
layout(std430, binding = PBGI_BIND_START_NODE) readonly buffer StartNode { uint start_node[]; };
layout(std430, binding = PBGI_BIND_STATE) buffer State { uvec4 state[]; };
layout(std430, binding = PBGI_BIND_PENDING) buffer Pending { uint pending; };
layout(std430, binding = PBGI_BIND_SPLAT) readonly buffer Splat { float splat_radius[]; };

uniform uint n_recv;        // receivers in this tile
uniform uint first;         // first receiver of this dispatch (within the tile)
uniform int m;              // micro-buffer side
uniform float stop_multiple;
uniform float omega_pix;    // 2π/m² (Eq. 5)
uniform uint n_nodes;
uniform int use_lists;      // 0: classic (start = root), 1: CSR start lists
uniform int init;           // 1 on the first pass: start from the first start node
uniform int iter_budget;    // loop iterations per receiver and pass
uniform float disc_cone;    // splat nodes whose normal cone half-angle ≤ this [rad] as discs, others as spheres
uniform uint object_first;  // nodes from here on are the receiving object's surfels (pipeline/gather/surfels.py)
uniform float object_stop;  // the stop rule's multiple for the object's nodes (its silhouettes: finer clusters)
uniform float object_near;  // near field: an object leaf less than object_near × its splat radius above the
                            // receiver's tangent plane is not splatted (its own surfel, its neighbours)

const uint NONE = 0xFFFFFFFFu;

void main() {
    uint k = first + gl_GlobalInvocationID.x;
    if (k >= n_recv) return;
    uint s1 = use_lists != 0 ? start_off[k + 1u] : 1u;
    uvec4 st = init != 0 ? uvec4(use_lists != 0 ? start_off[k] : 0u, NONE, 0u, 0u) : state[k];
    uint s = st.x, i = st.y, end = st.z, count = st.w;
    if (s >= s1) { if (init != 0) state[k] = st; return; }

    uint base = k * uint(m * m);
    vec3 p = recv_a[k].xyz;
    vec3 n = recv_b[k].xyz;
    vec3 t, b;
    pbgi_frame(n, t, b);
    int iters = 0;
    while (s < s1 && iters < iter_budget) {
        iters++;
        if (i == NONE) {                                   // enter the next start node's sub-tree
            i = use_lists != 0 ? start_node[s] : 0u;
            if (i >= n_nodes) { s++; i = NONE; continue; }
            end = pbgi_nodes[i].skip;
        }
        if (i >= end) { s++; i = NONE; continue; }
        Node nd = pbgi_nodes[i];
        count++;
        vec3 v = pbgi_center(nd) - p;
        float dist = length(v);
        uint next = nd.skip;
        if (!pbgi_horizon_cull(v, nd.radius, n) && !pbgi_backface_cull(v, dist, nd.radius, nd.cone)) {
            float om = pbgi_node_solid_angle(dist, nd.radius);
            bool leaf = pbgi_is_leaf(nd);
            bool stop = pbgi_stop(om, leaf, i >= object_first ? object_stop : stop_multiple, omega_pix);
            vec3 ax; float half_angle;
            pbgi_cone_decode(nd.cone, ax, half_angle);
            float rs = splat_radius[i];
            bool skip_near = false;
            if (stop && i >= object_first) {               // the object's own surfels: near-field rules
                float h = dot(v, n);
                if (leaf) skip_near = h < object_near * rs;
                else if (half_angle > disc_cone && h < nd.radius) stop = false;   // a curved cluster
                                                           // across the tangent plane: refine it
            }
            if (skip_near) {
            } else if (stop) {
                vec3 vl = vec3(dot(v, t), dot(v, b), dot(v, n));
                if (half_angle <= disc_cone)
                    iters += pbgi_splat_disc(base, m, vl, dist, rs, vec3(dot(ax, t), dot(ax, b), dot(ax, n)),
                                             pbgi_color(nd));
                else
                    iters += pbgi_splat(base, m, vl, dist, rs, pbgi_color(nd));
            } else {
                next = i + 1u;
            }
        }
        i = next;
    }
    state[k] = uvec4(s, i, end, count);
    if (s < s1) atomicAdd(pending, 1u);
}
