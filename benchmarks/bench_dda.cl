/*
 * The peer of benchmarks/bench_dda.py: a plain single-level DDA, kernels/traversal.py steps 1-5 written the
 * straightforward way (one work-item per pixel, scalar code, one cell per step, a branch per family, no empty-space
 * skipping). Not a product path, and deliberately not built on kernels/cl/ray.h: it is what one would write
 * without fruxel. Of the scalar plain versions tried it is the fastest on PoCL (per-family private arrays indexed
 * by the stepped family ran about 4.7x slower, float4 lanes per family about 2x slower). Written as first_hit's
 * walk is, 16 rays per work-item in vector lanes, a plain DDA ran 2.7x faster than this one: that layout is part of
 * what first_hit gains over it (benchmarks/PERF_NOTES.md).
 *
 * Arithmetic: IEEE float32 without contraction, every crossing from its boundary index with traversal.py's
 * formulas (t = (u o_z - o_x) / (d_x - u d_z) for u, likewise v, t = (z - o_z) / d_z for z), so its cells are
 * first_hit's bit for bit.
 *
 *   grid  float8  (u_0, v_0, du, dv, z_near, dz, z_far, 0)        traversal.grid_params
 *   cam   float16 (fx, fy, cx, cy, R row-major, optical centre)  traversal.camera_params
 *   n     int4    (W, H, D, 1)
 */
#pragma OPENCL FP_CONTRACT OFF

/* floor(x) clamped to [0, hi] (NaN gives 0). */
int clamp_floor(float x, const int hi)
{
    x = (x >= 0.0f) ? x : 0.0f;
    return (int)((x <= (float)hi) ? x : (float)hi);
}

int sgn(const float x) { return (x > 0.0f) ? 1 : ((x < 0.0f) ? -1 : 0); }

/* Crossing of u- (or v-) boundary m: t = (u o_z - o_x) / (d_x - u d_z), +inf where the ray does not approach it
 * from its side (s (d_x - u d_z) <= 0: the root lies behind the apex). */
float cross_uv(const float u0, const float du, const int m, const float oz, const float ox, const float dx,
               const float dz, const int s)
{
    const float u = u0 + (float)m * du;
    const float den = dx - u * dz;
    return ((float)s * den > 0.0f) ? (u * oz - ox) / den : INFINITY;
}

/* Crossing of z-boundary m: t = (z - o_z) / d_z, +inf for a ray parallel to the slices. */
float cross_z(const float zn, const float dzc, const int m, const float oz, const float dz, const int s)
{
    const float z = zn + (float)m * dzc;
    return ((float)s * dz > 0.0f) ? (z - oz) / dz : INFINITY;
}

/* The entry-face normal (grid frame, unit, facing the camera) of family f entered with sign s through the boundary
 * of value b (u or v; unused for z): kernels/traversal.py. */
void face_normal(const int f, const float s, const float b, __global float* nrm)
{
    if (f == 2) {
        nrm[0] = 0.0f;
        nrm[1] = 0.0f;
        nrm[2] = -s;
        return;
    }
    const float inv = 1.0f / sqrt(1.0f + b * b);
    nrm[0] = f == 0 ? -s * inv : 0.0f;
    nrm[1] = f == 1 ? -s * inv : 0.0f;
    nrm[2] = s * b * inv;
}

/*
 * plain_first_hit_kernel: one work-item per pixel (x, y), global size the image rounded up to the local size. The
 * outputs of first_hit (kernels/cl/first_hit.cl), (h, w) row-major:
 *   labels uchar (D, H, W), 0 = empty; label int32, 0 on a miss; cell int64, -1 on a miss; depth float32 (the entry
 *   point's z in the viewing camera), 0 on a miss; normal float32 (h, w, 3) entry-face normal, 0 on a miss.
 */
__kernel void plain_first_hit_kernel(__global const uchar* labels, const float8 g, const float16 c, const int4 n,
                                     const int w, const int h, __global int* out_label, __global long* out_cell,
                                     __global float* out_depth, __global float* out_normal)
{
    const int x = get_global_id(0), y = get_global_id(1);
    if (x >= w || y >= h) return;
    const size_t pix = (size_t)y * w + x;
    __global float* nrm = out_normal + 3 * pix;
    out_label[pix] = 0;
    out_cell[pix] = -1;
    out_depth[pix] = 0.0f;
    nrm[0] = nrm[1] = nrm[2] = 0.0f;

    /* Ray in the grid frame; t is the depth in the viewing camera. */
    const float px = ((float)x + 0.5f - c.s2) / c.s0, py = ((float)y + 0.5f - c.s3) / c.s1;
    const float dx = c.s4 * px + c.s5 * py + c.s6;
    const float dy = c.s7 * px + c.s8 * py + c.s9;
    const float dz = c.sa * px + c.sb * py + c.sc;
    const float ox = c.sd, oy = c.se, oz = c.sf;
    const float u0 = g.s0, v0 = g.s1, du = g.s2, dv = g.s3, zn = g.s4, dzc = g.s5, zf = g.s6;

    /* 1. Clip to the frustum's six half-spaces a t + b >= 0 (left, right, top, bottom, near, far). */
    const float pa[6] = {dx - u0 * dz, -dx + -u0 * dz, dy - v0 * dz, -dy + -v0 * dz, dz, -dz};
    const float pb[6] = {ox - u0 * oz, -ox + -u0 * oz, oy - v0 * oz, -oy + -v0 * oz, oz - zn, -oz + zf};
    float t_lo = 0.0f, t_hi = INFINITY;
    int plane = -1;
    for (int p = 0; p < 6; ++p) {
        const float t = -pb[p] / pa[p];
        if (pa[p] == 0.0f) {
            if (pb[p] < 0.0f) return;
        } else if (pa[p] > 0.0f) {
            if (t > t_lo) {
                t_lo = t;
                plane = p;
            }
        } else if (t < t_hi) {
            t_hi = t;
        }
    }
    if (t_lo >= t_hi) return;

    /* 2. Entry cell, clamped; the entry plane's own index set exactly. */
    const float ex = ox + t_lo * dx, ey = oy + t_lo * dy, ez = oz + t_lo * dz;
    int i = clamp_floor((ex / ez - u0) / du, n.x - 1);
    int j = clamp_floor((ey / ez - v0) / dv, n.y - 1);
    int k = clamp_floor((ez - zn) / dzc, n.z - 1);
    if (plane == 0) i = 0;
    if (plane == 1) i = n.x - 1;
    if (plane == 2) j = 0;
    if (plane == 3) j = n.y - 1;
    if (plane == 4) k = 0;
    if (plane == 5) k = n.z - 1;

    /* 3. Step signs. */
    const int si = sgn(dx * oz - dz * ox), sj = sgn(dy * oz - dz * oy), sk = sgn(dz);

    /* 4. Next crossing of each family, from the index of the boundary ahead. */
    float ti = cross_uv(u0, du, i + (si > 0), oz, ox, dx, dz, si);
    float tj = cross_uv(v0, dv, j + (sj > 0), oz, oy, dy, dz, sj);
    float tk = cross_z(zn, dzc, k + (sk > 0), oz, dz, sk);

    /* 5. Cell by cell: test, then step the family with the nearest crossing (ties u, v, z). The entry face: the
     * family of the last step (-1 before any) and the value of the boundary it crossed. */
    float t_entry = t_lo, face_b = 0.0f;
    int face = -1;
    const int max_steps = n.x + n.y + n.z + 3;
    for (int it = 0; it < max_steps; ++it) {
        const size_t cell = ((size_t)k * n.y + j) * n.x + i;
        const uchar v = labels[cell];
        if (v) {
            out_label[pix] = v;
            out_cell[pix] = (long)cell;
            out_depth[pix] = t_entry;
            if (face >= 0) {
                face_normal(face, (float)(face == 0 ? si : (face == 1 ? sj : sk)), face_b, nrm);
            } else if (plane >= 0) {
                /* the clip plane: left, top, near are entered forwards (+1), right, bottom, far backwards */
                const float side = (plane & 1) ? -1.0f : 1.0f;
                face_normal(plane >> 1, side, side * ((plane >> 1) == 0 ? u0 : v0), nrm);
            } else {
                /* a camera inside an occupied cell hits it at t = 0, facing the ray */
                const float dn = sqrt(dx * dx + dy * dy + dz * dz);
                nrm[0] = -dx / dn;
                nrm[1] = -dy / dn;
                nrm[2] = -dz / dn;
            }
            return;
        }
        if (ti <= tj && ti <= tk) {
            if (!(ti < t_hi)) return;
            t_entry = ti;
            face = 0;
            face_b = u0 + (float)(i + (si > 0)) * du;
            i += si;
            if (i < 0 || i >= n.x) return;
            ti = cross_uv(u0, du, i + (si > 0), oz, ox, dx, dz, si);
        } else if (tj <= tk) {
            if (!(tj < t_hi)) return;
            t_entry = tj;
            face = 1;
            face_b = v0 + (float)(j + (sj > 0)) * dv;
            j += sj;
            if (j < 0 || j >= n.y) return;
            tj = cross_uv(v0, dv, j + (sj > 0), oz, oy, dy, dz, sj);
        } else {
            if (!(tk < t_hi)) return;
            t_entry = tk;
            face = 2;
            k += sk;
            if (k < 0 || k >= n.z) return;
            tk = cross_z(zn, dzc, k + (sk > 0), oz, dz, sk);
        }
    }
}
