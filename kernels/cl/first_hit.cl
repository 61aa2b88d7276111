/*
 * first_hit: the first occupied cell along each pixel's ray (kernels/traversal.py), a tile of LANES rays at a time
 * by walk.h's trace_tile(), then each pixel's label, cell, depth and entry-face normal.
 *
 * Build options (-D, from kernels/cl/occupancy.py): those of walk.h and ray.h.
 */
#include "walk.h"

/* Entry-face normal (grid frame, unit, facing the camera) of family f entered with sign s through the boundary
 * of value b (u or v; unused for z): kernels/traversal.py. */
RAY_INLINE void face_normal(const ri f, const rf s, const rf b, rf* nx, rf* ny, rf* nz)
{
    const rf inv = 1.0f / sqrt(1.0f + b * b);
    *nx = (f == FAMILY_U) ? -s * inv : (rf)(0.0f);
    *ny = (f == FAMILY_V) ? -s * inv : (rf)(0.0f);
    *nz = (f == FAMILY_Z) ? -s : s * b * inv;
}

/* One row of a tile's outputs: 4 pixels from pixel index pix on. */
RAY_INLINE void store_row(const int4 label, const long4 cell, const float4 depth, const float4 nx, const float4 ny,
                          const float4 nz, const size_t pix, __global int* out_label, __global long* out_cell,
                          __global float* out_depth, __global float* out_normal)
{
    vstore4(label, 0, out_label + pix);
    vstore4(cell, 0, out_cell + pix);
    vstore4(depth, 0, out_depth + pix);
    vstore4((float4)(nx.x, ny.x, nz.x, nx.y), 0, out_normal + 3 * pix);
    vstore4((float4)(ny.y, nz.y, nx.z, ny.z), 0, out_normal + 3 * pix + 4);
    vstore4((float4)(nz.z, nx.w, ny.w, nz.w), 0, out_normal + 3 * pix + 8);
}

/*
 * trace_first_hit_kernel: one work-item per tile of TILE x TILE_H pixels (x0, y0) = (TILE gx, TILE_H gy) of the
 * viewing camera and batch item b = get_global_id(2).
 *   global size (ceil(ceil(w / TILE) / lx) lx, ceil(ceil(h / TILE_H) / ly) ly, B), local size (lx, ly, 1);
 *   work-items past the image do nothing.
 * Inputs: labels uchar (B, D, H, W); field ushort (B, gd.z, gd.y, gd.x), the walk's fields (occupancy.cl).
 * Outputs, (B, h, w) row-major, pixel index (b * h + y) * w + x:
 *   label  int32   label of the first occupied cell, 0 on a miss
 *   cell   int64   flat cell index (k * H + j) * W + i, -1 on a miss
 *   depth  float32 z of the entry point in the viewing camera (the ray parameter t), 0 on a miss
 *   normal float32 (B, h, w, 3) entry-face normal in the grid frame, zeros on a miss
 */
__kernel void trace_first_hit_kernel(__global const uchar* labels, __global const ushort* field, const int4 gd,
                                     const float8 grid, const float16 cam, const int4 n, const int w, const int h,
                                     const int max_iter, __global int* out_label, __global long* out_cell,
                                     __global float* out_depth, __global float* out_normal)
{
    const int x0 = get_global_id(0) * TILE, y0 = get_global_id(1) * TILE_H, b = get_global_id(2);
    if (x0 >= w || y0 >= h) return;
    __global const uchar* m0 = labels + (size_t)b * n.x * n.y * n.z;
    const size_t pix0 = ((size_t)b * h + y0) * w + x0;
    const int whole = x0 + TILE <= w && y0 + TILE_H <= h;
    TileHits th;
    if (!trace_tile(x0, y0, w, h, field + (size_t)b * gd.x * gd.y * gd.z, gd, grid, cam, n, max_iter,
                    &th) && whole) {
        /* No ray of the tile enters the frustum. */
        for (int row = 0; row < TILE_H; ++row) {
            const size_t p = pix0 + (size_t)row * w;
            store_row((int4)(0), (long4)(-1), (float4)(0.0f), (float4)(0.0f), (float4)(0.0f), (float4)(0.0f), p,
                      out_label, out_cell, out_depth, out_normal);
        }
        return;
    }
    const ri hit = th.hit;
    const cell_v cell = walk_cell(th.i, th.j, th.k, n);
    ri label;
#define G(l) label.l = hit.l ? m0[cell.l] : 0;
    WALK_LANES(G)
#undef G

    /* The entry face: a step's boundary is the hit cell's side facing the camera, i (s > 0) or i + 1 (s < 0); a
     * clip plane is entered forwards (left, top, near: +1) or backwards (right, bottom, far: -1). */
    const Rays* r = &th.r;
    const ri stepped = (th.entry >= 0) & (th.entry < ENTRY_PLANE);
    const ri cplane = th.entry - ENTRY_PLANE;
    const ri fam = stepped ? th.entry : ((th.entry >= ENTRY_PLANE) ? cplane >> 1 : (ri)(ENTRY_INSIDE));
    const rf side = ((cplane & 1) != 0) ? (rf)(-1.0f) : (rf)(1.0f);
    const rf s = stepped ? ((fam == FAMILY_U) ? r->su : ((fam == FAMILY_V) ? r->sv : r->sz)) : side;
    const rf bu = r->u0 + RAY_CVF(th.i + (r->su < 0.0f ? (ri)(1) : (ri)(0))) * r->du;
    const rf bv = r->v0 + RAY_CVF(th.j + (r->sv < 0.0f ? (ri)(1) : (ri)(0))) * r->dv;
    const rf bval = stepped ? ((fam == FAMILY_U) ? bu : bv) : side * ((fam == FAMILY_U) ? (rf)(r->u0) : (rf)(r->v0));
    rf nx, ny, nz;
    face_normal(fam, s, bval, &nx, &ny, &nz);
    /* A camera inside an occupied cell hits it at t = 0, facing the ray. */
    const rf dn = sqrt(r->dx * r->dx + r->dy * r->dy + r->dz * r->dz);
    const ri inside = fam == ENTRY_INSIDE;
    nx = hit ? (inside ? -r->dx / dn : nx) : (rf)(0.0f);
    ny = hit ? (inside ? -r->dy / dn : ny) : (rf)(0.0f);
    nz = hit ? (inside ? -r->dz / dn : nz) : (rf)(0.0f);
    const rf depth = hit ? th.t_entry : (rf)(0.0f);
    label = hit ? label : (ri)(0);
    /* -1 where no hit (kept narrow: vectors of 64-bit lanes wider than the target's made PoCL 3.0 drop the kernel
     * when it reloaded it from its cache) */
#if WIDE_INDEX
    const cell_v cellout = RAY_CVL(hit) ? cell : (cell_v)(-1);
#else
    const cell_v cellout = hit ? cell : (cell_v)(-1);
#endif

    if (whole) {
#define ROW(q, r)                                                                                                \
    store_row(label.q, convert_long4(cellout.q), depth.q, nx.q, ny.q, nz.q, pix0 + (r) * w, out_label, out_cell,   \
              out_depth, out_normal);
        ROW(s0123, 0)
        ROW(s4567, 1)
#if LANES == 16
        ROW(s89ab, 2)
        ROW(scdef, 3)
#endif
#undef ROW
        return;
    }
    /* A tile cut by the image's edge: the pixels inside it one by one. */
#define EDGE(l, q)                                                                                               \
    {                                                                                                            \
        const int x = x0 + ((q) & 3), y = y0 + ((q) >> 2);                                                      \
        if (x < w && y < h) {                                                                                    \
            const size_t pix = ((size_t)b * h + y) * w + x;                                                      \
            out_label[pix] = label.l;                                                                            \
            out_cell[pix] = (long)cellout.l;                                                                     \
            out_depth[pix] = depth.l;                                                                            \
            out_normal[3 * pix] = nx.l;                                                                          \
            out_normal[3 * pix + 1] = ny.l;                                                                      \
            out_normal[3 * pix + 2] = nz.l;                                                                      \
        }                                                                                                        \
    }
    EDGE(s0, 0) EDGE(s1, 1) EDGE(s2, 2) EDGE(s3, 3) EDGE(s4, 4) EDGE(s5, 5) EDGE(s6, 6) EDGE(s7, 7)
#if LANES == 16
    EDGE(s8, 8) EDGE(s9, 9) EDGE(sa, 10) EDGE(sb, 11) EDGE(sc, 12) EDGE(sd, 13) EDGE(se, 14) EDGE(sf, 15)
#endif
#undef EDGE
}
