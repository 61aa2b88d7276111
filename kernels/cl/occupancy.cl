/*
 * Occupancy: float scores -> uint8 label volumes (SPEC section 2), and the coarse occupancy pyramid that the
 * traversal (first_hit.cl) uses for empty-space skipping.
 *
 * Build options (-D):
 *   SCORE_HALF / SCORE_FLOAT / SCORE_DOUBLE   the scores' element type (exactly one is defined)
 *   NUM_CHANNELS, MODE                        channel count C and occupancy rule of label_scores_kernel
 *   BLOCK                                     edge of a pyramid block in cells (kernels/traversal.py)
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
 * build_pyramid_kernel: one work-item per coarse cell (I, J, K) of batch item b: 1 when any of its fine cells (a
 * block of BLOCK^3, cut at the volume's far edges) is nonzero, else 0.
 *   global size (ceil(Wc / lx) lx, Hc, Dc * B), local size (lx, 1, 1); (Dc, Hc, Wc) = ceil((D, H, W) / BLOCK)
 *   fine    uchar (B, D, H, W)    labels or the level below
 *   coarse  uchar (B, Dc, Hc, Wc) out
 * The loops have a fixed trip count and clamp indices at the far edges instead of testing them (OR-ing a cell
 * twice changes nothing), so the body is straight-line code that PoCL vectorises across work-items.
 */
__kernel void build_pyramid_kernel(__global const uchar* fine, __global uchar* coarse, const int4 n, const int4 nc)
{
    const int I = get_global_id(0), J = get_global_id(1), KB = get_global_id(2);
    if (I >= nc.x) return;
    const int K = KB % nc.z, b = KB / nc.z;
    __global const uchar* f = fine + (size_t)b * n.x * n.y * n.z;
    const int i0 = I * BLOCK, j0 = J * BLOCK, k0 = K * BLOCK;
    uchar acc = 0;
#pragma unroll
    for (int kk = 0; kk < BLOCK; ++kk) {
        const int k = (k0 + kk < n.z) ? k0 + kk : n.z - 1;
#pragma unroll
        for (int jj = 0; jj < BLOCK; ++jj) {
            const int j = (j0 + jj < n.y) ? j0 + jj : n.y - 1;
            __global const uchar* row = f + ((size_t)k * n.y + j) * n.x;
#pragma unroll
            for (int ii = 0; ii < BLOCK; ++ii) acc |= row[(i0 + ii < n.x) ? i0 + ii : n.x - 1];
        }
    }
    coarse[(((size_t)b * nc.z + K) * nc.y + J) * nc.x + I] = acc ? 1 : 0;
}
