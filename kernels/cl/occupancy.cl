/*
 * Occupancy: float scores -> uint8 label volumes (conventions section 2), and the distance field that the first-hit walk
 * (walk.h) uses for empty-space skipping.
 *
 * Build options (-D):
 *   SCORE_HALF / SCORE_FLOAT / SCORE_DOUBLE   the scores' element type (exactly one is defined)
 *   NUM_CHANNELS, MODE                        channel count C and occupancy rule of label_scores_kernel
 *   GROUP_LOG, DIST_CAP, FIELD_GAP, AXIS       the walk's field (below)
 */

#ifdef SCORE_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double real;
#define LOAD(p, i) ((p)[i])
#define SCORE_T double
#elif defined(SCORE_HALF)
typedef float real;
/* half is a storage-only type without cl_khr_fp16: vload_half widens it exactly. */
#define LOAD(p, i) vload_half((i), (p))
#define SCORE_T half
#else
typedef float real;
#define LOAD(p, i) ((p)[i])
#define SCORE_T float
#endif

/*
 * label_scores_kernel: one work-item per cell and batch item.
 *   global size (ceil(cells / l) l, B), local size (l, 1), cells = D * H * W; work-items past the end do nothing.
 *   scores  SCORE_T (B, NUM_CHANNELS, D, H, W) logits or probabilities, NCDHW, channel 0 = empty
 *   labels  uchar   (B, D, H, W) out: 0 where empty, else the argmax over channels 1..C-1 (first on ties)
 *   MODE (-D) 0: argmax rule (occupied when that channel's score beats channel 0 strictly; ties go to 0);
 *             1: logits with threshold (occupied when 1 - softmax(scores)[0] >= threshold);
 *             2: probabilities with threshold (occupied when 1 - scores[0] >= threshold).
 * The channel count and the mode are build options so that the channel loop unrolls into straight-line code,
 * which PoCL vectorises across work-items (the host checks NUM_CHANNELS <= 256 so labels fit in uchar).
 * Precision: float, or double for double scores.
 */
__kernel void label_scores_kernel(__global const SCORE_T* scores, __global uchar* labels, const long cells,
                               const real threshold)
{
    const long cell = get_global_id(0);
    const long b = get_global_id(1);
    if (cell >= cells) return;
    __global const SCORE_T* p = scores + b * NUM_CHANNELS * cells + cell;
    const real s0 = LOAD(p, 0);
    real best = LOAD(p, cells);
    int arg = 1;
#pragma unroll
    for (int c = 2; c < NUM_CHANNELS; ++c) {
        const real v = LOAD(p, c * cells);
        arg = (v > best) ? c : arg;
        best = (v > best) ? v : best;
    }
#if MODE == 0
    const int occupied = best > s0;
#elif MODE == 1
    /* 1 - p(empty) as the non-empty mass over the total, not as 1 - p(empty): the subtraction would round a
     * small occupancy to 0 (as the Warp backend, kernels/wp/occupancy.py, computes it). */
    const real m = (s0 > best) ? s0 : best;
    real rest = 0;
#pragma unroll
    for (int c = 1; c < NUM_CHANNELS; ++c) rest += exp(LOAD(p, c * cells) - m);
    const int occupied = rest / (exp(s0 - m) + rest) >= threshold;
#else
    const int occupied = (1 - s0) >= threshold;
#endif
    labels[b * cells + cell] = occupied ? (uchar)arg : (uchar)0;
}

/*
 * The field of the first-hit walk (walk.h), per group of 2 x 2 x 2 cells (GROUP_LOG = 1):
 *   d     the chessboard distance, in groups, to the nearest group that holds an occupied cell, capped at DIST_CAP
 *         (0: the group holds one; d > 0: every group within d - 1 of it is empty, so a ray may leave that cube in
 *         one jump). Outside the grid counts as empty.
 *   mask  which of the group's cells are occupied: bit (i & 1) + 2 (j & 1) + 4 (k & 1) for cell (i, j, k), so the
 *         walk tests a cell without reading the labels.
 * stored as one ushort, d << 8 | mask, so that the walk reads both with one load. Built on every call from the
 * labels: one kernel marks occupied groups (and their masks), then three separable passes, one per axis, each
 * d(p) = min over |m| <= DIST_CAP of max(|m|, d_in(p + m e_axis)) (the chessboard distance is the largest of the
 * per-axis offsets, so the passes compose exactly); the last pass writes the field.
 *
 * Layouts (occupancy.py's field_layout), per batch item, in elements: GD slices of gd.y = GH + 1 rows of
 * gd.x = GWP + FIELD_GAP elements: GD = ceil(D / 2), GH = ceil(H / 2), GWP = ceil(W / 2) rounded up to a multiple
 * of 16. The field (ushort) starts at the first row. The passes' buffers (uchar: the distances so far, the masks)
 * have `lead` elements before the first row and as many after the last: a pass loads its neighbours DIST_CAP rows
 * or slices away unconditionally (memory the buffer owns) and ignores them where they lie outside the field, so
 * PoCL vectorises the passes across work-items. Everything but the GH x ceil(W / 2) groups of a slice is padding
 * that reads as empty: each row's gap (and the lead's last FIELD_GAP elements) lets the x pass load a row's
 * neighbours without masks, and the extra row keeps the slices of a z pass off a 4 KiB stride (loads a multiple
 * of 4 KiB apart compete for the same L1 cache sets).
 *
 * Build options (-D): GROUP_LOG (1), DIST_CAP (0 turns skipping off: every group reads d = 0), FIELD_GAP
 * (>= DIST_CAP), AXIS (1 or 2, of chessboard_yz_kernel) and PASS_WIDE (1 when the passes' buffers hold 2^31
 * elements or more: their offsets in 64 bits; 32-bit offsets keep the z pass's addressing short).
 */
#if PASS_WIDE
typedef long pass_index;
#else
typedef int pass_index;
#endif
#if GROUP_LOG != 1
#error "the field's masks hold the 8 cells of a 2 x 2 x 2 group: GROUP_LOG must be 1"
#endif

/* Bits s (cells at even x) and s + 1 (odd x) of the masks of 8 groups, from a row of 16 cells. */
#define PAIR_BITS(v, s)                                                                                          \
    ((as_uchar8((v).even != (uchar8)(0)) & (uchar8)(1 << (s))) | (as_uchar8((v).odd != (uchar8)(0)) & (uchar8)(2 << (s))))

/*
 * mark_groups_kernel: one work-item per 16 consecutive groups of a row, plus one per row for its gap.
 *   global size (GWP / 16 + 1, GH + 1, GD * B); n int4 (W, H, D, 1), gd int4 (GWP + FIELD_GAP, GH + 1, GD, 1)
 *   labels uchar (B, D, H, W) in; out (passes' layout): dist 0 where the group holds an occupied cell, DIST_CAP
 *   elsewhere and in the padding; masks the groups' masks (0 in the padding).
 */
__kernel void mark_groups_kernel(__global const uchar* labels, __global uchar* dist, __global uchar* masks,
                                 const int4 n, const int4 gd, const int lead)
{
    const int gx = get_global_id(0) * 16, gy = get_global_id(1), gzb = get_global_id(2);
    const int gz = gzb % gd.z, b = gzb / gd.z;
    if (gx == 0 && gy == 0 && gzb == 0) vstore16((uchar16)(DIST_CAP), 0, dist + lead - FIELD_GAP);
    const size_t at = lead + ((size_t)gzb * gd.y + gy) * gd.x + gx;
    const int x0 = gx << GROUP_LOG, y0 = gy << GROUP_LOG, z0 = gz << GROUP_LOG;
    if (y0 >= n.y || gx + 16 > gd.x - FIELD_GAP) {
        /* the padding: the extra row, the gap */
        vstore16((uchar16)(DIST_CAP), 0, dist + at);
        vstore16((uchar16)(0), 0, masks + at);
        return;
    }
    __global const uchar* vol = labels + (size_t)b * n.x * n.y * n.z;
    /* the group's far cells clamped into the grid: a clamped copy sets a mask bit of a cell the walk never visits */
    const int y1 = min(y0 + 1, n.y - 1), z1 = min(z0 + 1, n.z - 1);
    if (x0 + 32 <= n.x) {
        /* 32 cells of each of the 4 cell rows of the 16 groups */
        __global const uchar* r0 = vol + ((size_t)z0 * n.y + y0) * n.x + x0;
        __global const uchar* r1 = vol + ((size_t)z0 * n.y + y1) * n.x + x0;
        __global const uchar* r2 = vol + ((size_t)z1 * n.y + y0) * n.x + x0;
        __global const uchar* r3 = vol + ((size_t)z1 * n.y + y1) * n.x + x0;
        const uchar16 a0 = vload16(0, r0), a1 = vload16(0, r1), a2 = vload16(0, r2), a3 = vload16(0, r3);
        const uchar16 b0 = vload16(1, r0), b1 = vload16(1, r1), b2 = vload16(1, r2), b3 = vload16(1, r3);
        const uchar16 mask = (uchar16)(PAIR_BITS(a0, 0) | PAIR_BITS(a1, 2) | PAIR_BITS(a2, 4) | PAIR_BITS(a3, 6),
                                       PAIR_BITS(b0, 0) | PAIR_BITS(b1, 2) | PAIR_BITS(b2, 4) | PAIR_BITS(b3, 6));
        vstore16(mask, 0, masks + at);
        vstore16(select((uchar16)(DIST_CAP), (uchar16)(0), mask != (uchar16)(0)), 0, dist + at);
        return;
    }
    /* The general case: group by group, cells past the grid's far edges left out (groups past it are empty). */
    for (int q = 0; q < 16; ++q) {
        const int xa = x0 + (q << GROUP_LOG);
        uchar mask = 0;
        for (int z = z0; z < min(z0 + 2, n.z); ++z)
            for (int y = y0; y < min(y0 + 2, n.y); ++y)
                for (int x = xa; x < min(xa + 2, n.x); ++x)
                    mask |= (vol[((size_t)z * n.y + y) * n.x + x] != 0) << ((x - xa) + 2 * (y - y0) + 4 * (z - z0));
        masks[at + q] = mask;
        dist[at + q] = mask ? 0 : DIST_CAP;
    }
}

/* min and max of uchars as selects: PoCL 3.0 calls its min / max builtins out of line in these kernels, per element */
#define UMIN(a, b) ((a) < (b) ? (a) : (b))
#define UMAX(a, b) ((a) > (b) ? (a) : (b))

/*
 * chessboard_x_kernel: the x pass, one work-item per group (PoCL vectorises the work-items of a row).
 *   global size (GWP, GH + 1, GD * B); in, out uchar (passes' layout):
 *   out(p) = min over |m| <= DIST_CAP of max(|m|, in(p +- m)); the row's gap and the lead read DIST_CAP.
 */
__kernel void chessboard_x_kernel(__global const uchar* in, __global uchar* out, const int4 gd, const int lead)
{
    const size_t at = lead + ((size_t)get_global_id(2) * gd.y + get_global_id(1)) * gd.x + get_global_id(0);
    uchar best = in[at];
#pragma unroll
    for (int m = 1; m <= DIST_CAP; ++m) {
        const uchar near = UMIN(in[at - m], in[at + m]);
        const uchar far = UMAX((uchar)m, near);
        best = UMIN(best, far);
    }
    out[at] = best;
}

/*
 * chessboard_yz_kernel (AXIS 1: y, 2: z): the pass along y or z, one work-item per group.
 *   global size (GWP, GH + 1, GD * B); in uchar (passes' layout): out(p) = min over |m| <= DIST_CAP of
 *   max(|m|, in(p +- m e_AXIS)), where a neighbour outside the slice (y) or the batch item's field (z) reads
 *   DIST_CAP. The y pass writes out (uchar, passes' layout); the z pass writes the field (ushort, from its first row)
 *   d << 8 | masks.
 */
#if AXIS == 2
__kernel void chessboard_yz_kernel(__global const uchar* in, __global const uchar* masks, __global ushort* field,
                                   const int4 gd, const int lead)
#else
__kernel void chessboard_yz_kernel(__global const uchar* in, __global uchar* out, const int4 gd, const int lead)
#endif
{
    const int gy = get_global_id(1), gzb = get_global_id(2);
    const pass_index row = ((pass_index)gzb * gd.y + gy) * gd.x + (pass_index)get_global_id(0);
    const pass_index at = lead + row;
#if AXIS == 1
    const int p = gy, len = gd.y;
    const pass_index stride = gd.x;
#else
    const int p = gzb % gd.z, len = gd.z;
    const pass_index stride = (pass_index)gd.x * gd.y;
#endif
    /* Neighbours are loaded whatever they hold (within the buffer's lead and tail); outside the field they are
     * taken as 255 (an OR with all bits set), which changes nothing since every value is at most DIST_CAP. The
     * masks are uniform over the work-group; set up front, in uchars, they leave the loop byte operations that
     * PoCL vectorises 64 wide (computed in the loop they made it widen every byte to 32 bits: 2.6x slower). */
    uchar lo_out[DIST_CAP + 1], hi_out[DIST_CAP + 1];
#pragma unroll
    for (int m = 1; m <= DIST_CAP; ++m) {
        lo_out[m] = p < m ? 255 : 0;
        hi_out[m] = p + m >= len ? 255 : 0;
    }
    uchar best = in[at];
#pragma unroll
    for (int m = 1; m <= DIST_CAP; ++m) {
        const uchar near = in[at - m * stride] | lo_out[m], far = in[at + m * stride] | hi_out[m];
        const uchar either = UMIN(near, far);
        const uchar apart = UMAX((uchar)m, either);
        best = UMIN(best, apart);
    }
#if AXIS == 1
    out[at] = best;
#else
    field[row] = (ushort)(best << 8 | masks[at]);
#endif
}
