/*
 * VMS shell (conventions section 4): mark every cell that is the first hit of some pixel of some camera, then build the
 * output volume. The first hits come from walk.h's trace_tile(), as first_hit.cl's do.
 *
 * Build options (-D, from kernels/cl/occupancy.py): those of walk.h and ray.h.
 *
 * mask  uchar (B, D, H, W): 1 for kept cells. Set to 0 by the host, then only ever written with 1, so the races
 *       between rays that hit the same cell are benign.
 */
#include "walk.h"

/*
 * mark_shell_kernel: one work-item per tile of TILE x TILE_H pixels of one viewing camera and batch item b; sets the
 * mask at the tile's first hits. Global and local sizes, and all arguments but the first (first_hit's labels) and
 * the last, as first_hit's (first_hit.cl).
 */
__kernel void mark_shell_kernel(__global const ushort* field, const int4 gd,
                                const float8 grid, const float16 cam, const int4 n, const int w, const int h,
                                const int max_iter, __global uchar* mask)
{
    const int x0 = get_global_id(0) * TILE, y0 = get_global_id(1) * TILE_H, b = get_global_id(2);
    if (x0 >= w || y0 >= h) return;
    const size_t cells = (size_t)n.x * n.y * n.z;
    TileHits th;
    if (!trace_tile(x0, y0, w, h, field + (size_t)b * gd.x * gd.y * gd.z, gd, grid, cam, n, max_iter,
                    &th))
        return;
    const cell_v cell = walk_cell(th.i, th.j, th.k, n);
    __global uchar* m = mask + b * cells;
#define G(l) if (th.hit.l) m[cell.l] = 1;
    WALK_LANES(G)
#undef G
}

/*
 * mark_columns_kernel: the fast path for the grid's own camera at native resolution, whose pixel (i, j) looks
 * straight down column (j, i) from the near plane (traversal.is_own_view): one work-item per column (i, j) and
 * batch item b marks the column's first occupied cell, which is exactly that pixel's first hit.
 *   global size (ceil(W / lx) lx, H, B), local size (lx, 1, 1)
 *   labels uchar (B, D, H, W), mask uchar (B, D, H, W)
 */
__kernel void mark_columns_kernel(__global const uchar* labels, const int4 n, __global uchar* mask)
{
    const int i = get_global_id(0), j = get_global_id(1), b = get_global_id(2);
    if (i >= n.x) return;
    const size_t plane = (size_t)n.x * n.y;
    const size_t base = b * plane * n.z + (size_t)j * n.x + i;
    for (int k = 0; k < n.z; ++k) {
        if (labels[base + k * plane]) {
            mask[base + k * plane] = 1;
            return;
        }
    }
}

/*
 * write_shell_kernel_<bytes>: the output volume, on raw element bits (so one kernel per element size serves every
 * dtype: integer labels, float16/32/64 scores). One work-item per element (cell, channel c, batch item b):
 *   out[b, c, cell] = mask[b, cell] ? in[b, c, cell] : (c == 0 ? empty0 : empty1)
 *   global size (ceil(cells / l) l, C, B), local size (l, 1, 1), cells = D * H * W
 *   in, out  (B, C, D, H, W) elements of `bytes` bytes (C = 1 for labels), row-major
 *   mask     uchar (B, D, H, W)
 *   empty0, empty1  bit patterns of the removed cell's channel 0 and other channels: 0 and 0 for labels; the
 *                   dtype's 0 and EMPTY_LOGIT for logits; its 1 and 0 for probabilities.
 */
#define SHELL_SELECT(NAME, T)                                                                                  \
    __kernel void NAME(__global const T* in, __global const uchar* mask, __global T* out, const long cells,   \
                       const T empty0, const T empty1)                                                         \
    {                                                                                                          \
        const long cell = get_global_id(0);                                                                    \
        if (cell >= cells) return;                                                                             \
        const long c = get_global_id(1), b = get_global_id(2), C = get_global_size(1);                        \
        const long e = (b * C + c) * cells + cell;                                                             \
        out[e] = mask[b * cells + cell] ? in[e] : (c == 0 ? empty0 : empty1);                                  \
    }
SHELL_SELECT(write_shell_kernel_1, uchar)
SHELL_SELECT(write_shell_kernel_2, ushort)
SHELL_SELECT(write_shell_kernel_4, uint)
SHELL_SELECT(write_shell_kernel_8, ulong)
