/*
 * First-hit ray traversal through a fruxel grid: kernels/traversal.py step by step, with exact empty-space
 * skipping over a coarse occupancy pyramid. shell.cl and soft_first_hit.cl are compiled after this file and reuse
 * parts of it: shell.cl trace_pixel() and Hit; soft_first_hit.cl Ray, setup_ray(), pick() and LANES, and its
 * crossing_of() repeats one lane of crossings() bit for bit. Keep those stable.
 *
 * Build options (-D), all set by the host from kernels/traversal.py so that no number is copied here:
 *   BLOCK, LOG_BLOCK                 edge of a pyramid block in cells, and its log2 (BLOCK is a power of 2)
 *   LEVELS                           pyramid levels the traversal uses: 1 (cells only, the plain loop),
 *                                    2 (+ blocks of BLOCK cells a side) or 3 (+ super-blocks of BLOCK^2)
 *   FAMILY_U, FAMILY_V, FAMILY_Z     plane-family numbers, which are also the tie order
 *   -cl-fp32-correctly-rounded-divide-sqrt (always), and never fast or relaxed math.
 *
 * Frames and layouts (see kernels/traversal.py, fruxel/grid.py):
 *   grid  float8  (u_0, v_0, du, dv, z_near, dz, z_far, 0)             traversal.grid_params
 *   cam   float16 (fx, fy, cx, cy, R row-major, optical centre)       traversal.camera_params, R camera-to-grid
 *   n     int4    (W, H, D, 1): cells per family
 *   labels uchar  (B, D, H, W): 0 = empty, else the label (flat cell index (k * H + j) * W + i)
 *   pyr1   uchar  (B, ceil(D/BLOCK), ceil(H/BLOCK), ceil(W/BLOCK)): 1 where a block holds an occupied cell
 *   pyr2   uchar  (B, ceil(D/BLOCK^2), ...): the same one level up (a 1-byte dummy when LEVELS < 3)
 *
 * Every per-family quantity is a vector whose lane f is family f (x = u / column i, y = v / row j, z = slice k,
 * w unused), so picking the first lane among equal minima is the tie order u, v, z.
 *
 * Arithmetic: IEEE float32, no contraction. Every plane crossing comes from the one function crossings(), from
 * its boundary index, so a block boundary's crossing is bit-equal to the same plane's crossing as a cell
 * boundary; that is what makes the skipping exact (it reproduces the plain loop's state cell for cell).
 */
#pragma OPENCL FP_CONTRACT OFF

#if FAMILY_U != 0 || FAMILY_V != 1 || FAMILY_Z != 2
#error "lane f of the per-family vectors holds family f: FAMILY_U, FAMILY_V, FAMILY_Z must be 0, 1, 2"
#endif
#if (1 << LOG_BLOCK) != BLOCK
#error "BLOCK must be 1 << LOG_BLOCK"
#endif

#define LANES ((int4)(0, 1, 2, 3))
/* PoCL leaves calls that are not forced inline as calls, builtins included (select, min, floor, any, ...):
 * helpers are always_inline and the hot paths use operators (vector ?: is a lane-wise select) instead. */
#define INLINE inline __attribute__((always_inline))
#define NO_FAMILY (-1)

/* One ray in the grid frame with the per-family constants of step 4:
 * boundary value of index m of family f: b = base[f] + m * step[f]  (u_m, v_m or z_m)
 * crossing of that boundary:            t = (b A[f] - C[f]) / (E[f] - b F[f])
 * which is (u o_z - o_x) / (d_x - u d_z) for u, the same with y for v, and (z - o_z) / d_z for z. */
typedef struct {
    float4 d;    /* direction (x, y, z, 0); the origin is in C */
    float4 base, step;
    float4 A, C, E, F;
    float4 sf;   /* step signs as floats */
    int4 s;      /* step signs s_i, s_j, s_k (step 3); lane w is 0 */
    int4 n;      /* cells per family, (W, H, D, 1) */
} Ray;

typedef struct {
    int label;     /* label of the hit cell, 0 on a miss */
    int4 cell;     /* (i, j, k) of the hit cell */
    float depth;   /* t of the entry point */
    float4 normal; /* entry-face normal, grid frame */
} Hit;

/* Next crossing of the boundaries nb, +inf for a family that is never crossed: sign 0, or a boundary the ray
 * does not approach from the current side (s (E - b F) <= 0; there the formula's root lies at z <= 0, behind
 * the apex, and is no crossing of the frustum's plane: kernels/traversal.py step 4). */
INLINE float4 crossings(const Ray* r, const int4 nb)
{
    const float4 b = r->base + convert_float4(nb) * r->step;
    const float4 den = r->E - b * r->F;
    const float4 t = (b * r->A - r->C) / den;
    return (r->sf * den > 0.0f) ? t : (float4)(INFINITY);
}

/* The boundary ahead of a cell starting at index a with the given stride (cells of one pyramid level). */
INLINE int4 next_boundary(const int4 a, const int4 s, const int stride, const int4 n)
{
    const int4 up = a + stride;
    return (s > 0) ? ((up < n) ? up : n) : a;
}

INLINE int pick(const int4 v, const int f) { return f == 0 ? v.x : (f == 1 ? v.y : v.z); }

/* Occupancy of the cell of a pyramid level (cells of 1 << sh fine cells) containing fine index a. */
INLINE uchar cell_at(__global const uchar* map, const int4 a, const int sh, const int4 n)
{
    const int4 c = a >> sh;
    const int4 m = ((n - 1) >> sh) + 1;
    return map[((size_t)c.z * m.y + c.y) * m.x + c.x];
}

/* floor(x) clamped to [0, hi] (NaN gives 0): truncation is floor once x >= 0. */
INLINE int clamp_floor(float x, const int hi)
{
    x = (x >= 0.0f) ? x : 0.0f;
    x = (x <= (float)hi) ? x : (float)hi;
    return (int)x;
}

INLINE float sgn(const float x) { return (x > 0.0f) ? 1.0f : ((x < 0.0f) ? -1.0f : 0.0f); }

/* Ray of pixel (x, y) (step 0), clipped to the frustum (step 1), its entry cell (step 2) and signs (step 3).
 * Returns 0 when the ray misses the frustum; else fills r, the clip interval and the entry plane (0..5 in the
 * order left, right, top, bottom, near, far; -1 when the camera is inside and there is none). */
INLINE int setup_ray(const int x, const int y, const float8 g, const float16 c, const int4 n,
                     Ray* r, int4* entry, float* t_lo_out, float* t_hi_out, int* plane_out)
{
    /* Independent divisions are grouped into vector divisions (one instruction each on a CPU). */
    const float2 pxy = ((float2)((float)x, (float)y) + 0.5f - c.s23) / c.s01;
    const float px = pxy.x, py = pxy.y;
    const float dx = c.s4 * px + c.s5 * py + c.s6;
    const float dy = c.s7 * px + c.s8 * py + c.s9;
    const float dz = c.sa * px + c.sb * py + c.sc;
    const float ox = c.sd, oy = c.se, oz = c.sf;
    const float u0 = g.s0, v0 = g.s1, zn = g.s4, zf = g.s6;
    const float uw = -u0, vh = -v0;

    /* Cyrus-Beck: a = n . d, b = n . o + c for left, right, top, bottom, near, far; candidates t = -b / a. */
    const float8 pa = (float8)(dx - u0 * dz, -dx + uw * dz, dy - v0 * dz, -dy + vh * dz, dz, -dz, 1.0f, 1.0f);
    const float8 pb = (float8)(ox - u0 * oz, -ox + uw * oz, oy - v0 * oz, -oy + vh * oz, oz - zn, -oz + zf,
                               0.0f, 0.0f);
    const float8 pt = -pb / pa;
    float t_lo = 0.0f, t_hi = INFINITY;
    int plane = -1;
#define CLIP(P, A, B, T)                                   \
    if ((A) == 0.0f) {                                     \
        if ((B) < 0.0f) return 0;                          \
    } else if ((A) > 0.0f) {                               \
        if ((T) > t_lo) { t_lo = (T); plane = (P); }       \
    } else {                                               \
        t_hi = ((T) < t_hi) ? (T) : t_hi;                  \
    }
    CLIP(0, pa.s0, pb.s0, pt.s0)
    CLIP(1, pa.s1, pb.s1, pt.s1)
    CLIP(2, pa.s2, pb.s2, pt.s2)
    CLIP(3, pa.s3, pb.s3, pt.s3)
    CLIP(4, pa.s4, pb.s4, pt.s4)
    CLIP(5, pa.s5, pb.s5, pt.s5)
#undef CLIP
    if (t_lo >= t_hi) return 0;

    /* Entry cell from the entry point, clamped; the entry plane's own family is set exactly. */
    const float ex = ox + t_lo * dx, ey = oy + t_lo * dy, ez = oz + t_lo * dz;
    const float2 uv = (float2)(ex, ey) / ez;
    const float4 fe = (float4)(uv.x - u0, uv.y - v0, ez - zn, 0.0f) / (float4)(g.s2, g.s3, g.s5, 1.0f);
    int4 e = (int4)(clamp_floor(fe.x, n.x - 1), clamp_floor(fe.y, n.y - 1), clamp_floor(fe.z, n.z - 1), 0);
    if (plane >= 0) {
        const int4 side = (plane & 1) ? n - 1 : (int4)(0);
        e = (LANES == (int4)(plane >> 1)) ? side : e;
    }

    const float si = sgn(dx * oz - dz * ox), sj = sgn(dy * oz - dz * oy), sk = sgn(dz);
    r->d = (float4)(dx, dy, dz, 0.0f);
    r->base = (float4)(u0, v0, zn, 0.0f);
    r->step = (float4)(g.s2, g.s3, g.s5, 0.0f);
    r->A = (float4)(oz, oz, 1.0f, 0.0f);
    r->C = (float4)(ox, oy, oz, 0.0f);
    r->E = (float4)(dx, dy, dz, 0.0f);
    r->F = (float4)(dz, dz, 0.0f, 0.0f);
    r->sf = (float4)(si, sj, sk, 0.0f);
    r->s = convert_int4(r->sf);
    r->n = n;
    *entry = e;
    *t_lo_out = t_lo;
    *t_hi_out = t_hi;
    *plane_out = plane;
    return 1;
}

/* Entry-face normal (grid frame, unit, facing the camera): family f, step sign s, boundary value b. */
INLINE float4 face_normal(const int f, const float s, const float b)
{
    if (f == FAMILY_Z) return (float4)(0.0f, 0.0f, -s, 0.0f);
    const float inv = 1.0f / sqrt(1.0f + b * b);
    return (f == FAMILY_U) ? (float4)(-s * inv, 0.0f, s * b * inv, 0.0f)
                           : (float4)(0.0f, -s * inv, s * b * inv, 0.0f);
}

/* The boundary after the one ahead (one more cell of the same stride). Its crossing is computed a step early,
 * off the critical path of the loop; where it lies outside the grid its value is never used, because the step
 * across the boundary ahead leaves the grid and misses first. */
INLINE int4 after_boundary(const int4 a, const int4 s, const int stride, const int4 n)
{
    const int4 up = a + 2 * stride;
    return (s > 0) ? ((up < n) ? up : n) : a - stride;
}

/* Steps 4 and 5 with empty-space skipping. The state is, per family, the first fine index a of the current
 * cell of the current level (cells of 1 << sh fine cells, aligned), the boundary ahead nb, its crossing t and
 * the crossing tn of the boundary after it. At level 0 this is exactly the plain loop's state. A level-L cell
 * is empty when its pyramid entry is 0:
 *   - in an empty cell whose parent is empty too, go up a level (the ray leaves the parent through one of its
 *     boundaries, and every fine crossing before that is of empty cells);
 *   - step as the plain loop does, with the level's boundaries: smallest crossing, ties u, v, z; miss on
 *     t >= t_hi or leaving the grid;
 *   - entering an occupied coarse cell at t_entry through family f, go down a level: f's sub-cell is the one at
 *     the entry side; every other family starts at the sub-cell where it came into the coarse cell (or where
 *     the ray entered the grid) and advances past its sub-boundaries crossed before t_entry (at t_entry too
 *     for families before f in the tie order, which the plain loop steps first): the plain loop's state after
 *     the same crossing.
 * Returns 1 and fills hit on a hit, 0 on a miss. max_iter only guards against an endless loop (the index moves
 * bound the plain loop to W + H + D steps). */
INLINE int trace(const Ray* r, const int4 entry, const float t_lo, const float t_hi, const int plane,
                 __global const uchar* m0, __global const uchar* m1, __global const uchar* m2,
                 const int max_iter, Hit* hit)
{
    const int4 s = r->s, n = r->n;
    int4 a = entry;
    int L = 0, sh = 0;
    int4 nb = next_boundary(a, s, 1, n);
    float4 t = crossings(r, nb);
    float4 tn = crossings(r, after_boundary(a, s, 1, n));
    float t_entry = t_lo;
    /* Entry face: family of the last step and the boundary it crossed, or the clip plane before any step. */
    int ef = (plane >= 0) ? (plane >> 1) : NO_FAMILY;
    int stepped = 0;
    int4 crossed = (int4)(0); /* boundary indices ahead before the last step; lane ef was crossed */
    int up = 1; /* the current cell's parent may be empty (it is new) */

    for (int it = 0; it < max_iter; ++it) {
        __global const uchar* map = (L == 0) ? m0 : ((L == 1) ? m1 : m2);
        const uchar v = cell_at(map, a, sh, n);
        if (v) {
            if (L == 0) {
                float4 nrm;
                if (ef == NO_FAMILY) {
                    nrm = -r->d / sqrt(r->d.x * r->d.x + r->d.y * r->d.y + r->d.z * r->d.z);
                } else if (stepped) {
                    const int eb = pick(crossed, ef);
                    const float bu = r->base.x + (float)eb * r->step.x, bv = r->base.y + (float)eb * r->step.y;
                    nrm = face_normal(ef, (float)pick(s, ef), (ef == FAMILY_U) ? bu : bv);
                } else {
                    /* The clip plane: left, top, near are entered forwards (+1), right, bottom, far backwards. */
                    const float side = (plane & 1) ? -1.0f : 1.0f;
                    nrm = face_normal(ef, side, side * ((ef == FAMILY_U) ? r->base.x : r->base.y));
                }
                hit->label = v;
                hit->cell = a;
                hit->depth = t_entry;
                hit->normal = nrm;
                return 1;
            }
            /* Down a level, into the sub-cell the ray is in at t_entry. */
            const int sh2 = sh - LOG_BLOCK, S2 = 1 << sh2;
            const int4 top = a + (1 << sh);
            const int4 hi = (top < n) ? top : n;
            /* Search start: the sub-cell at the side where the ray came in, or, for families whose coarse
             * index has not changed since the ray entered the grid, the sub-cell of the entry cell (the ray never
             * crossed the sub-boundaries behind it, whose formula roots lie behind the apex). */
            int4 c = (s < 0) ? ((hi - 1) >> sh2) << sh2 : a;
            c = ((a >> sh) == (entry >> sh)) ? (entry >> sh2) << sh2 : c;
            int4 nb2 = next_boundary(c, s, S2, n);
            float4 t2 = crossings(r, nb2);
            const int4 movable = (LANES != (int4)(ef)) & (s != 0);
            const int4 tie_taken = LANES < (int4)(ef);
            for (;;) {
                const int4 inside = (s > 0) ? (nb2 < hi) : (nb2 > a);
                const int4 behind = tie_taken ? (t2 <= t_entry) : (t2 < t_entry);
                const int4 adv = movable & inside & behind;
                if ((adv.x | adv.y | adv.z) == 0) break;
                c += adv & (s * S2);
                nb2 = next_boundary(c, s, S2, n);
                t2 = crossings(r, nb2);
            }
            a = c;
            nb = nb2;
            t = t2;
            tn = crossings(r, after_boundary(c, s, S2, n));
            sh = sh2;
            --L;
            up = 0;
            continue;
        }
        /* Up while the parent is empty too. */
        while (up && L + 1 < LEVELS) {
            __global const uchar* pmap = (L == 0) ? m1 : m2;
            if (cell_at(pmap, a, sh + LOG_BLOCK, n)) break;
            ++L;
            sh += LOG_BLOCK;
            a = (a >> sh) << sh;
            nb = next_boundary(a, s, 1 << sh, n);
            t = crossings(r, nb);
            tn = crossings(r, after_boundary(a, s, 1 << sh, n));
        }
        /* Step: the family with the smallest crossing, ties u, v, z. */
        const int f = (t.x <= t.y && t.x <= t.z) ? 0 : ((t.y <= t.z) ? 1 : 2);
        const float tf = (f == 0) ? t.x : ((f == 1) ? t.y : t.z);
        if (!(tf < t_hi)) return 0;
        const int4 fm = LANES == (int4)(f);
        const int S = 1 << sh;
        crossed = nb;
        a += fm & (s * S);
        const int4 out = fm & ((a < 0) | (a >= n));
        if (out.x | out.y | out.z) return 0;
        nb = fm ? next_boundary(a, s, S, n) : nb;
        t = fm ? tn : t;
        tn = fm ? crossings(r, after_boundary(a, s, S, n)) : tn;
        t_entry = tf;
        ef = f;
        stepped = 1;
        /* A boundary of the parent level was crossed: the parent is new and may be empty. */
        const int4 new_parent = fm & ((crossed & ((S << LOG_BLOCK) - 1)) == 0);
        up = (new_parent.x | new_parent.y | new_parent.z) != 0;
    }
    return 0;
}

/*
 * The first hit of pixel (x, y) of batch item b (1 and *hit set, or 0 on a miss): this item's slices of the label
 * volume and of its pyramid levels, then setup_ray() and trace(). The body of trace_first_hit_kernel and of
 * shell.cl's mark_shell_kernel, whose arguments it takes as they come.
 */
INLINE int trace_pixel(const int x, const int y, const int b, __global const uchar* labels,
                       __global const uchar* pyr1, __global const uchar* pyr2, const float8 grid, const float16 cam,
                       const int4 n, const int max_iter, Hit* hit)
{
    const int4 n1 = ((n - 1) >> LOG_BLOCK) + 1;
    const int4 n2 = ((n - 1) >> (2 * LOG_BLOCK)) + 1;
    __global const uchar* m0 = labels + (size_t)b * n.x * n.y * n.z;
    __global const uchar* m1 = pyr1 + (size_t)b * n1.x * n1.y * n1.z;
    __global const uchar* m2 = (LEVELS > 2) ? pyr2 + (size_t)b * n2.x * n2.y * n2.z : pyr2;
    Ray r;
    int4 entry;
    float t_lo, t_hi;
    int plane;
    if (!setup_ray(x, y, grid, cam, n, &r, &entry, &t_lo, &t_hi, &plane)) return 0;
    return trace(&r, entry, t_lo, t_hi, plane, m0, m1, m2, max_iter, hit);
}

/*
 * trace_first_hit_kernel: one work-item per pixel (x, y) of the viewing camera and batch item b.
 *   global size (ceil(w / lx) lx, ceil(h / ly) ly, B), local size (lx, ly, 1): 2D pixel tiles, so that the
 *   rays of a work-group read neighbouring cells. Work-items past the image edge do nothing.
 * Outputs, (B, h, w) row-major, pixel index (b * h + y) * w + x:
 *   label  int32   label of the first occupied cell, 0 on a miss
 *   cell   int64   flat cell index (k * H + j) * W + i, -1 on a miss
 *   depth  float32 z of the entry point in the viewing camera (the ray parameter t), 0 on a miss
 *   normal float32 (B, h, w, 3) entry-face normal in the grid frame, zeros on a miss
 */
__kernel void trace_first_hit_kernel(__global const uchar* labels, __global const uchar* pyr1,
                                     __global const uchar* pyr2, const float8 grid, const float16 cam, const int4 n,
                                     const int w, const int h, const int max_iter, __global int* out_label,
                                     __global long* out_cell, __global float* out_depth, __global float* out_normal)
{
    const int x = get_global_id(0), y = get_global_id(1), b = get_global_id(2);
    if (x >= w || y >= h) return;
    Hit hit;
    const int found = trace_pixel(x, y, b, labels, pyr1, pyr2, grid, cam, n, max_iter, &hit);

    const size_t pix = ((size_t)b * h + y) * w + x;
    if (found) {
        out_label[pix] = hit.label;
        out_cell[pix] = ((long)hit.cell.z * n.y + hit.cell.y) * n.x + hit.cell.x;
        out_depth[pix] = hit.depth;
        out_normal[3 * pix] = hit.normal.x;
        out_normal[3 * pix + 1] = hit.normal.y;
        out_normal[3 * pix + 2] = hit.normal.z;
    } else {
        out_label[pix] = 0;
        out_cell[pix] = -1;
        out_depth[pix] = 0.0f;
        out_normal[3 * pix] = 0.0f;
        out_normal[3 * pix + 1] = 0.0f;
        out_normal[3 * pix + 2] = 0.0f;
    }
}
