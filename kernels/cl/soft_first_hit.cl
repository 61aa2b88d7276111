/*
 * soft_first_hit: expected first hit along each pixel's ray and its exact backward pass (see
 * kernels/cl/soft_first_hit.py for the outputs and the backward recursion; kernels/wp/soft_first_hit.py derives the
 * same two passes).
 *
 * One ray per work-item: the ray set-up and crossings are ray.h's (steps 0-4 of kernels/traversal.py, the same
 * arithmetic as first_hit.cl's walk), so both operations visit the same cells in the same order.
 *
 * Build options (-D), set by the host:
 *   those of ray.h (FAMILY_U/V/Z, from kernels/traversal.py)
 *   REAL_DOUBLE   1: accumulate in double (cl_khr_fp64, with cl_khr_int64_base_atomics for the scatter); 0: float
 *   NC            number of non-empty classes (C - 1): the per-ray class accumulators are a private array
 *   SPW           steps per word of the step tape (2 bits per step: the plane family crossed)
 *
 * Layouts (row-major), cells by flat index (k * H + j) * W + i, rays by r = (b * ncam + slot) * h * w + y * w + x:
 *   probs    real (B, NC + 1, D*H*W)     class probabilities, channel 0 = empty (p_0 clamped to [0, 1])
 *   classes  real (B, ncam, NC + 1, h*w) channel 0: miss = T_M = prod_m p_m0; channel c >= 1:
 *                                        acc_c = sum_m T_m p_mc = sum_m w_m q_mc (the renormalisation cancels)
 *   depth    real (B, ncam, h*w)         dsum / hit, hit = sum_{c>=1} acc_c (in channel order); 0 where
 *                                        hit <= REAL_MIN
 *   dsum     real (B, ncam, h*w)         sum_m T_m S_m t_m, S_m = sum_{c>=1} p_mc (t: z in the viewing camera)
 *   state    int  (R, 4)                 cells on the ray and (i, j, k) of the last one
 *   log_t    real (R)                    log T after the last cell: sum of log p_m0 over cells with p_m0 > 0
 *   tape     uint (R, words)             family of each step, SPW per word
 */
#define RAY_W 1
#include "ray.h"

/* Per-family int4 vectors: lane f is family f (x = u / column i, y = v / row j, z = slice k, w unused). */
#define LANES ((int4)(0, 1, 2, 3))
inline int pick(const int4 v, const int f) { return f == 0 ? v.x : (f == 1 ? v.y : v.z); }

#if REAL_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable
typedef double real;
#define REAL_MIN DBL_MIN
#else
typedef float real;
#define REAL_MIN FLT_MIN
#endif

inline float pickf(const float4 v, const int f) { return f == 0 ? v.x : (f == 1 ? v.y : v.z); }

/* The boundary ahead of (s > 0: index + 1) or behind (s > 0: index) cell index i for step sign s. */
inline int ahead(const int i, const int s) { return s > 0 ? i + 1 : i; }
inline int behind(const int i, const int s) { return s < 0 ? i + 1 : i; }

/* Scatter-add by compare-and-swap on the value's bits (OpenCL 1.2 has no floating-point atomic add). */
inline void atomic_add_real(volatile __global real* p, const real v)
{
#if REAL_DOUBLE
    union { ulong u; double f; } prev, next;
    do {
        prev.f = *p;
        next.f = prev.f + v;
    } while (atom_cmpxchg((volatile __global ulong*)p, prev.u, next.u) != prev.u);
#else
    union { uint u; float f; } prev, next;
    do {
        prev.f = *p;
        next.f = prev.f + v;
    } while (atomic_cmpxchg((volatile __global uint*)p, prev.u, next.u) != prev.u);
#endif
}

/* *p += v: skipped for 0 (most channels of a pixel the loss treats as a miss), plain when no two rays of the launch
 * share a cell (the grid's own view: each pixel owns a column), else by compare-and-swap. */
inline void scatter(volatile __global real* p, const real v, const int exclusive)
{
    if (v == (real)0) return;
    if (exclusive) *p += v;
    else atomic_add_real(p, v);
}

/*
 * Forward: one work-item per pixel (x, y) of camera slot `slot` and batch item b.
 *   global size (ceil(w / lx) lx, ceil(h / ly) ly, B), local size (lx, ly, 1); items past the image do nothing.
 * Visits the ray's cells in DDA order (plain loop, every cell): acc_c += T p_c, dsum += T S t, T *= p_0, where
 * S = sum_{c>=1} p_c; stops early only when T is 0 (or below REAL_MIN, flushed to 0). Then writes classes
 * (miss = T, acc), dsum and depth = dsum / hit. With save = 1 also writes state, log_t and tape.
 */
__kernel void accumulate_soft_hits_kernel(__global const real* probs, const float8 grid, const float16 cam,
                                          const int4 n, const int w, const int h, const int max_steps,
                                          const int slot, const int ncam, const int save, const int words,
                                          __global real* classes, __global real* depth, __global real* dsum,
                                          __global int* state, __global real* log_t, __global uint* tape)
{
    const int x = get_global_id(0), y = get_global_id(1), b = get_global_id(2);
    if (x >= w || y >= h) return;
    const size_t hw = (size_t)w * h, p = (size_t)y * w + x;
    const size_t cells = (size_t)n.x * n.y * n.z;
    const size_t r = ((size_t)b * ncam + slot) * hw + p;
    __global const real* pb = probs + (size_t)b * (NC + 1) * cells;

    real accv[NC];
    for (int c = 0; c < NC; ++c) accv[c] = (real)0;
    real ds = 0, tr = 1, logt = 0;
    int ncell = 0;
    int4 idx = (int4)(0);

    Rays ray;
    float t_lo, t_hi;
    int plane, iu, iv, iz;
    if (rays_setup((float)x, (float)y, grid, cam, n, &ray, &t_lo, &t_hi, &plane, &iu, &iv, &iz)) {
        idx = (int4)(iu, iv, iz, 0);
        const int4 s = (int4)((int)ray.su, (int)ray.sv, (int)ray.sz, 0);
        float4 tn = (float4)(cross_u(&ray, ahead(idx.x, s.x)), cross_v(&ray, ahead(idx.y, s.y)),
                             cross_z(&ray, ahead(idx.z, s.z)), INFINITY);
        float t_entry = t_lo;
        uint word = 0;
        for (int it = 0; it < max_steps; ++it) {
            const size_t cell = ((size_t)idx.z * n.y + idx.y) * n.x + idx.x;
            const real p0 = clamp(pb[cell], (real)0, (real)1);
            real occ = 0;
            for (int c = 0; c < NC; ++c) {
                const real pc = pb[(size_t)(c + 1) * cells + cell];
                accv[c] += tr * pc;
                occ += pc;
            }
            ds += tr * occ * (real)t_entry;
            ++ncell;
            if (save && p0 > (real)0) logt += log(p0);
            tr *= p0;
            if (tr < REAL_MIN) {
                /* Transmittance 0, or below the smallest normal number, where it is flushed to 0 (as FTZ arithmetic
                 * does): every later weight is 0, and the CPU is spared denormal arithmetic (~100x slower). */
                tr = 0;
                break;
            }
            const int f = (tn.x <= tn.y && tn.x <= tn.z) ? 0 : ((tn.y <= tn.z) ? 1 : 2);
            const float tf = pickf(tn, f);
            if (!(tf < t_hi)) break;
            const int sf = pick(s, f);
            const int nxt = pick(idx, f) + sf;
            if (nxt < 0 || nxt >= pick(n, f)) break;
            if (save) {
                const int st = ncell - 1;
                word |= (uint)f << (2 * (st % SPW));
                if (st % SPW == SPW - 1) {
                    tape[r * words + st / SPW] = word;
                    word = 0;
                }
            }
            const int4 fm = LANES == (int4)(f);
            idx = select(idx, (int4)(nxt), fm);
            t_entry = tf;
            tn = select(tn, (float4)(cross_f(&ray, f, ahead(nxt, sf))), fm);
        }
        if (save && (ncell - 1) % SPW != 0) tape[r * words + (ncell - 1) / SPW] = word;
    }

    __global real* cls = classes + ((size_t)b * ncam + slot) * (NC + 1) * hw + p;
    cls[0] = tr;
    for (int c = 0; c < NC; ++c) cls[(size_t)(c + 1) * hw] = accv[c];
    real hit = 0; /* sum_{c>=1} acc_c in channel order, as the backward sums the stored classes: the same bits */
    for (int c = 0; c < NC; ++c) hit += accv[c];
    /* No hit possible (or below REAL_MIN): depth 0, as first_hit's on a miss, and no 0 / 0. */
    depth[r] = hit > REAL_MIN ? ds / hit : (real)0;
    dsum[r] = ds;
    if (save) {
        state[4 * r] = ncell;
        state[4 * r + 1] = idx.x;
        state[4 * r + 2] = idx.y;
        state[4 * r + 3] = idx.z;
        log_t[r] = logt;
    }
}

/*
 * Backward: one work-item per pixel as in the forward; adds this launch's rays' gradient into grad.
 *
 * Per ray, from the upstream gradients g_classes (gm = channel 0, gc_c = channel c >= 1), g_depth and g_dsum:
 * the chain rule through depth = dsum / hit (hit > REAL_MIN; else depth is the constant 0) folds g_depth into
 *   gd = g_dsum + g_depth / hit,  cmn = -g_depth depth / hit   (the gradient of every acc_c through hit),
 * so that acc_c gets gc_c + cmn and dsum gets gd. Walks the forward's cells last to first by undoing the taped
 * steps, with T_m = exp(log T_{m+1} - log p_m0), u_m = cmn + gd t_m, a_m = sum_{c>=1} (gc_c + u_m) p_mc,
 * R_{M-1} = gm, R_{m-1} = a_m + p_m0 R_m:
 *   grad[0][m] += T_m R_m,  grad[c][m] += T_m (gc_c + u_m)   (scatter(): plain adds when exclusive = 1)
 * classes, g_classes (B, ncam, NC + 1, h*w); depth, g_depth, g_dsum (B, ncam, h*w); grad (B, NC + 1, D*H*W),
 * zeroed by the host before the first launch.
 */
__kernel void backpropagate_soft_hits_kernel(__global const real* probs, const float8 grid, const float16 cam,
                                             const int4 n, const int w, const int h, const int slot,
                                             const int ncam, const int exclusive, const int words,
                                             __global const int* state, __global const real* log_t,
                                             __global const uint* tape, __global const real* classes,
                                             __global const real* depth, __global const real* g_classes,
                                             __global const real* g_depth, __global const real* g_dsum,
                                             __global real* grad)
{
    const int x = get_global_id(0), y = get_global_id(1), b = get_global_id(2);
    if (x >= w || y >= h) return;
    const size_t hw = (size_t)w * h, p = (size_t)y * w + x;
    const size_t cells = (size_t)n.x * n.y * n.z;
    const size_t r = ((size_t)b * ncam + slot) * hw + p;
    const int ncell = state[4 * r];
    if (ncell == 0) return;

    const size_t ch = ((size_t)b * ncam + slot) * (NC + 1) * hw + p;
    real gc[NC];
    int any = 0;
    for (int c = 0; c < NC; ++c) {
        gc[c] = g_classes[ch + (size_t)(c + 1) * hw];
        any |= gc[c] != (real)0;
    }
    const real gm = g_classes[ch], gdep = g_depth[r];
    real gd = g_dsum[r], cmn = 0;
    if (gdep != (real)0) {
        real hit = 0; /* the forward's sum, same values in the same order: the same bits */
        for (int c = 0; c < NC; ++c) hit += classes[ch + (size_t)(c + 1) * hw];
        if (hit > REAL_MIN) {
            gd += gdep / hit;
            cmn = -gdep * depth[r] / hit;
        }
    }
    if (!any && gm == (real)0 && gd == (real)0 && cmn == (real)0) return; /* a pixel the loss ignores */

    Rays ray;
    float t_lo, t_hi;
    int plane, iu, iv, iz;
    rays_setup((float)x, (float)y, grid, cam, n, &ray, &t_lo, &t_hi, &plane, &iu, &iv, &iz);
    const int4 s = (int4)((int)ray.su, (int)ray.sv, (int)ray.sz, 0);
    __global const real* pb = probs + (size_t)b * (NC + 1) * cells;
    __global real* gb = grad + (size_t)b * (NC + 1) * cells;

    int4 idx = (int4)(state[4 * r + 1], state[4 * r + 2], state[4 * r + 3], 0);
    real logt = log_t[r];
    real rr = gm;
    for (int m = ncell - 1; m >= 0; --m) {
        int f = 0;
        float t = t_lo;
        if (m > 0) {
            const int st = m - 1;
            f = (int)((tape[r * words + st / SPW] >> (2 * (st % SPW))) & 3u);
            t = cross_f(&ray, f, behind(pick(idx, f), pick(s, f)));
        }
        const size_t cell = ((size_t)idx.z * n.y + idx.y) * n.x + idx.x;
        const real p0 = clamp(pb[cell], (real)0, (real)1);
        if (p0 > (real)0) logt -= log(p0);
        const real tr = exp(logt);
        const real u = cmn + gd * (real)t;
        real a = 0;
        for (int c = 0; c < NC; ++c) {
            const real g = gc[c] + u;
            a += g * pb[(size_t)(c + 1) * cells + cell];
            scatter(gb + (size_t)(c + 1) * cells + cell, tr * g, exclusive);
        }
        scatter(gb + cell, tr * rr, exclusive);
        rr = a + p0 * rr;
        if (m > 0) idx = select(idx, idx - s, LANES == (int4)(f));
    }
}
