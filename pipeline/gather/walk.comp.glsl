#version 430
// walk.comp.glsl — fill one micro-buffer per receiver (§5.2): for every start node s of receiver k's CSR
// list (start_off[k] .. start_off[k+1]) run the stackless depth-first walk of s's sub-tree (visit i;
// descend to i+1 or jump to skip[i]), culling a node and its sub-tree by the horizon and Fig. 5
// back-face tests, splatting it when the stop rule Ω(A) ≤ stop_multiple·Ω_pix holds or it is a leaf.
// Classic = one start node, the root (use_lists = 0). Flat nodes (normal cone ≤ disc_cone) are splatted
// as discs at any distance, the others as spheres (one call site, pbgi_splat_node: llvmpipe runs every inlined
// copy of a splat loop in every iteration, lanes masked or not). (A flat cluster whose
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
#define PBGI_LOBEBUFFER
#include "pbgi_common.glsl"

layout(local_size_x = 64) in;
layout(std430, binding = PBGI_BIND_START_OFF) readonly buffer StartOff { uint start_off[]; };
layout(std430, binding = PBGI_BIND_START_NODE) readonly buffer StartNode { uint start_node[]; };
layout(std430, binding = PBGI_BIND_STATE) buffer State { uvec4 state[]; };
layout(std430, binding = PBGI_BIND_PENDING) buffer Pending { uint pending; };
layout(std430, binding = PBGI_BIND_SPLAT) readonly buffer Splat { float splat_radius[]; };
layout(std430, binding = PBGI_BIND_RECV_C) readonly buffer RecvC { vec4 recv_c[]; };   // (base colour, lobe T)
layout(std430, binding = PBGI_BIND_RECV_D) readonly buffer RecvD { vec4 recv_d[]; };   // (unit eye direction, 0)

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
uniform uint object_first;  // nodes from here on are the receiving object's surfels (pipeline/relight/surfels.py)
uniform float object_stop;  // the stop rule's multiple for the object's nodes (its silhouettes: finer clusters)
uniform float object_near;  // near field: an object leaf less than object_near × its splat radius above the
                            // receiver's geometric plane (recv_e: the face's, not the smooth shading normal's, which
                            // tilts past it at silhouettes) and within object_reach × that radius of the receiver
                            // is not splatted (its own surfel, its neighbours); a farther leaf occludes at any
uniform float object_reach; // height (a concave part's far wall: without the reach, a band along the horizon)
// PBGI_WALK_LOBE (define, 0 or 1; walk.py compiles one program of each): 1 fills the lobe micro-buffers
// (pbgi_common.glsl PBGI_LOBEBUFFER) of the receivers with recv_c.w = T > 0 instead of the hemisphere buffers:
// frame (U, V, A), stop rule against the lobe texel's solid angle (2T/lobe_m)², nodes outside the lobe's cone
// (half-angle atan(T√2)) culled; the others are done at once. (Two programs, not a uniform: llvmpipe runs every
// branch of a loop body under a lane mask, so the hemisphere walk paid for the lobe splat's code and vice versa.)
uniform int lobe_m;         // lobe micro-buffer side
uniform float lobe_leaf_r;  // pbgi_lobe_tan: the cloud's median leaf splat radius [m] (0: T as given)
uniform float lobe_tmax;    // pbgi_lobe_tan: the largest T (2.5 = tan 68°)
// directional object nodes (surfels.py, a glossy object's bounces): object node i's radiance towards the unit
// direction w (from the node to the receiver) is obj_dir[(i − object_first)·S² + pbgi_oct_cell(w, S)], S =
// obj_dir_side; 0 = the node's colour (Lambert surfels, the room)
layout(std430, binding = PBGI_BIND_OBJ_DIRS) readonly buffer ObjDirs { vec4 obj_dir[]; };
uniform int obj_dir_side;

// PBGI_NODE_TEX (define: log2 of the texture's width; walk.py node_texels): the walk reads its nodes from a 2-D
// RGBA32UI texture instead of the node SSBO — node i is texels 3i, 3i+1, 3i+2 = (centre.xyz, radius),
// (right, skip, cone, splat radius), (colour.rgb, 0), the same bits. On llvmpipe an SSBO read at a per-lane index is
// a loop over the SIMD lanes of bounds-checked scalar loads, a texelFetch one vector gather (measured: 1.5× the node
// reads per CPU-second of a bare loop); unused texels are never fetched (the traversal reads two of the three).
#ifdef PBGI_NODE_TEX
uniform usampler2D node_tex;
uvec4 node_texel(uint j) {
    return texelFetch(node_tex, ivec2(int(j & ((1u << PBGI_NODE_TEX) - 1u)), int(j >> PBGI_NODE_TEX)), 0);
}
Node walk_node(uint i) {
    uvec4 a = node_texel(3u * i), b = node_texel(3u * i + 1u), c = node_texel(3u * i + 2u);
    return Node(b.x, b.y, uintBitsToFloat(a.x), uintBitsToFloat(a.y), uintBitsToFloat(a.z), uintBitsToFloat(c.x),
                uintBitsToFloat(c.y), uintBitsToFloat(c.z), uintBitsToFloat(a.w), b.z);
}
float walk_splat_radius(uint i) { return uintBitsToFloat(node_texel(3u * i + 1u).w); }
#else
Node walk_node(uint i) { return pbgi_nodes[i]; }
float walk_splat_radius(uint i) { return splat_radius[i]; }
#endif

vec3 node_radiance(uint i, Node nd, vec3 v, float dist) {
    if (obj_dir_side > 0 && i >= object_first)
        return obj_dir[(i - object_first) * uint(obj_dir_side * obj_dir_side) + pbgi_oct_cell(-v / dist, obj_dir_side)].rgb;
    return pbgi_color(nd);
}

const uint NONE = 0xFFFFFFFFu;

// The splat queue: the walk collects up to PBGI_SPLAT_QUEUE stopped nodes, then splats them in one loop. llvmpipe
// runs a shader's SIMD lanes (8 at 256 bits) in lock step and every branch of a loop body under a lane mask, so
// a splat inside the walk loop cost every lane a splat whenever one lane stopped a node (~40 % of the visits:
// nearly every iteration for 8 lanes); queued, the lanes splat together. The splat order per receiver is the
// walk order, as before: the micro-buffers are the same bit for bit.
#ifndef PBGI_SPLAT_QUEUE
#define PBGI_SPLAT_QUEUE 32
#endif

// Splat the stopped node i into the receiver's buffer at `base` (frame t, b, f; lobe T): texel iterations + 1.
int splat_stopped(uint i, vec3 p, vec3 t, vec3 b, vec3 f, uint base, float T) {
    Node nd = walk_node(i);
    vec3 v = pbgi_center(nd) - p;
    float dist = length(v);
    vec3 ax; float half_angle;
    pbgi_cone_decode(nd.cone, ax, half_angle);
    float rs = walk_splat_radius(i);
    vec3 vl = vec3(dot(v, t), dot(v, b), dot(v, f));
    vec3 al = vec3(dot(ax, t), dot(ax, b), dot(ax, f));
#ifdef PROF_SETUP_ONLY
    vec3 col = node_radiance(i, nd, v, dist);               // profiling: the node's re-read and frame, no splat
    if (dot(col, vec3(1.0)) + dot(vl, al) + rs + half_angle < -1.0e30) pbgi_mb[base] = vec4(col, dist);
    return 1;
#endif
#if PBGI_WALK_LOBE
    return pbgi_splat_lobe(base, lobe_m, T, vl, dist, rs, al, half_angle <= disc_cone, node_radiance(i, nd, v, dist));
#else
    return pbgi_splat_node(base, m, vl, dist, rs, al, half_angle <= disc_cone, node_radiance(i, nd, v, dist));
#endif
}

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
    vec3 t, b, f = n;                                      // the splat frame (t, b, f): (t, b, n) or (U, V, A)
    float om_pix = omega_pix, T = 0.0, cone_cos = -2.0, cone_sin = 0.0;
    if (PBGI_WALK_LOBE != 0) {
        f = pbgi_lobe_axis(n, recv_d[k].xyz);
        vec3 tn, bn;
        pbgi_frame(n, tn, bn);
        T = pbgi_lobe_tan(recv_c[k].w, base, m, lobe_m, vec3(dot(f, tn), dot(f, bn), dot(f, n)), lobe_leaf_r, lobe_tmax);
        if (!(T > 0.0)) { state[k] = uvec4(s1, NONE, 0u, count); return; }
        base = k * uint(lobe_m * lobe_m);
        float tex = 2.0 * T / float(lobe_m);
        om_pix = tex * tex;
        float cone = atan(T * 1.41421356);
        cone_cos = cos(cone);
        cone_sin = sin(cone);
    }
    pbgi_frame(f, t, b);
    int iters = 0;
    uint queue[PBGI_SPLAT_QUEUE];
    while (s < s1 && iters < iter_budget) {
        int nq = 0;
        while (nq < PBGI_SPLAT_QUEUE && s < s1 && iters < iter_budget) {
            iters++;
            if (i == NONE) {                                   // enter the next start node's sub-tree
                i = use_lists != 0 ? start_node[s] : 0u;
                if (i >= n_nodes) { s++; i = NONE; continue; }
                end = walk_node(i).skip;
            }
            if (i >= end) { s++; i = NONE; continue; }
            Node nd = walk_node(i);
    #if !defined(PROF_ITERS) && !defined(PROF_SPLATS)
            count++;
    #endif
            vec3 v = pbgi_center(nd) - p;
            float dist = length(v);
            uint next = nd.skip;
            bool outside_lobe = false;
            if (PBGI_WALK_LOBE != 0 && dist > nd.radius) {     // the sphere misses the lobe's cone: angle(v, A) >
                float sr = nd.radius / dist;                   // cone + asin(r/dist) (< π), in cosines
                outside_lobe = dot(v, f) / dist < cone_cos * sqrt(max(1.0 - sr * sr, 0.0)) - cone_sin * sr;
            }
    #ifdef PROF_NOBACK
            if (!outside_lobe && !pbgi_horizon_cull(v, nd.radius, n)) {
    #else
            if (!outside_lobe && !pbgi_horizon_cull(v, nd.radius, n) && !pbgi_backface_cull(v, dist, nd.radius, nd.cone)) {
    #endif
                float om = pbgi_node_solid_angle(dist, nd.radius);
                bool leaf = pbgi_is_leaf(nd);
                bool stop = pbgi_stop(om, leaf, i >= object_first ? object_stop : stop_multiple, om_pix);
                bool skip_near = false;
                if (stop && i >= object_first) {               // the object's own surfels: near-field rules
                    float h = dot(v, recv_e[k].xyz);           // height above the receiver's geometric plane
                    vec3 ax; float half_angle;
                    pbgi_cone_decode(nd.cone, ax, half_angle);
                    if (leaf) {
                        float rs = walk_splat_radius(i);
                        skip_near = h < object_near * rs && dist < object_reach * rs;
                    } else if (half_angle > disc_cone && h < nd.radius) stop = false;   // a curved cluster across
                                                               // the tangent plane: refine it
                }
                if (skip_near) {
                } else if (stop) {
    #ifdef PROF_SPLATS
                    count++;
    #endif
    #ifndef PROF_NOSPLAT
                    queue[nq++] = i;
    #endif
                } else {
                    next = i + 1u;
                }
            }
            i = next;
        }
#ifdef PROF_QUEUE_ONLY                                    // profiling: the queue's pushes and reads, no splat
        float acc = 0.0;
        for (int j = 0; j < nq; ++j) { acc += float(queue[j]); iters++; }
        if (acc < -1.0) pbgi_mb[base] = vec4(acc);
#else
        for (int j = 0; j < nq; ++j)                           // the one splat call site
            iters += splat_stopped(queue[j], p, t, b, f, base, T);
#endif
    }
#ifdef PROF_ITERS
    count += uint(iters);
#endif
    state[k] = uvec4(s, i, end, count);
    if (s < s1) atomicAdd(pending, 1u);
}
