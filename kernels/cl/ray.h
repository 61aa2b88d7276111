/*
 * ray.h: the part of kernels/traversal.py that every OpenCL walk shares, written once for a vector width:
 * a pixel's ray (step 0), its clip to the frustum (step 1), its entry cell (step 2), its step signs (step 3) and
 * the crossing of a plane by index (step 4). first_hit.cl and shell.cl use it 8 or 16 rays at a time (through
 * walk.h), soft_first_hit.cl one ray at a time.
 *
 * Include it once per program (runtime.source() resolves the #include) after defining
 *   RAY_W   1 (scalar: one ray per work-item), 8 or 16 (one ray per lane of float8 / int8 or float16 / int16)
 * It defines, for that width:
 *   rf, ri           float / int, or floatN / intN (one lane per ray)
 *   RAY_CVF, RAY_CVI conversions to rf / ri
 *   Rays             the rays' constants: direction, step signs, origin and the grid's constants
 *   rays_clip()      steps 0-1; returns the mask of rays that enter the frustum
 *   rays_entry()     steps 2-3 for the rays rays_clip() let in
 *   rays_setup()     both
 *   ray_any()        whether any lane of a mask is set
 *   cross_u/v/z()    step 4 for one family: the crossing of boundary m, +inf when the ray does not cross it
 *   cross_f()        the same for a family chosen at run time (scalar width only)
 * Masks are ri values: 1 / 0 at width 1, -1 / 0 (all bits) for vectors, as OpenCL's comparisons give them;
 * combine them with & | and !, never ~, so that every width reads them alike.
 *
 * Build options (-D, from kernels/cl/occupancy.py, all from kernels/traversal.py): FAMILY_U, FAMILY_V, FAMILY_Z.
 *
 * Arithmetic: IEEE float32 without contraction, every operation in the order kernels/traversal.py writes it, so
 * that both widths, and every kernel, give a ray the same bits. Layouts:
 *   g  float8  (u_0, v_0, du, dv, z_near, dz, z_far, 0)          traversal.grid_params
 *   c  float16 (fx, fy, cx, cy, R row-major, optical centre)    traversal.camera_params, R camera-to-grid
 *   n  int4    (W, H, D, 1): cells per family
 */
#pragma OPENCL FP_CONTRACT OFF

#if FAMILY_U != 0 || FAMILY_V != 1 || FAMILY_Z != 2
#error "families are numbered u, v, z = 0, 1, 2 (also the tie order)"
#endif

#if RAY_W == 1
typedef float rf;
typedef int ri;
#define RAY_CVF(x) ((float)(x))
#define RAY_CVI(x) ((int)(x))
#elif RAY_W == 8
typedef float8 rf;
typedef int8 ri;
#define RAY_CVF convert_float8
#define RAY_CVI convert_int8
#elif RAY_W == 16
typedef float16 rf;
typedef int16 ri;
#define RAY_CVF convert_float16
#define RAY_CVI convert_int16
#else
#error "RAY_W must be 1, 8 or 16"
#endif

/* PoCL leaves calls that are not forced inline as calls: every helper is always_inline. */
#define RAY_INLINE inline __attribute__((always_inline))

typedef struct {
    rf dx, dy, dz;    /* direction in the grid frame, unnormalised: t is the depth in the viewing camera */
    rf su, sv, sz;    /* step signs s_i, s_j, s_k as floats (1, -1 or 0; step 3) */
    float ox, oy, oz; /* origin (the optical centre) */
    float u0, v0, du, dv, zn, dzc; /* u_0, v_0, du, dv, z_near, dz */
} Rays;

RAY_INLINE rf ray_sign(const rf x) { return (x > 0.0f) ? (rf)(1.0f) : ((x < 0.0f) ? (rf)(-1.0f) : (rf)(0.0f)); }

/* floor(x) clamped to [0, hi] (NaN gives 0): truncation is floor once x >= 0. */
RAY_INLINE ri ray_clamp_floor(rf x, const int hi)
{
    x = (x >= 0.0f) ? x : (rf)(0.0f);
    x = (x <= (float)hi) ? x : (rf)((float)hi);
    return RAY_CVI(x);
}

/* Step 4: t = (b A - C) / (E - b F) for the boundary value b = base + m step, +inf unless s (E - b F) > 0 (a
 * boundary the ray does not approach from its side: the root lies behind the apex). u: A = o_z, C = o_x,
 * E = d_x, F = d_z; v likewise with y; z: A = 1, C = o_z, E = d_z, F = 0. */
#define RAY_CROSSING(base, step, A, C, E, F, s, m)                                                                \
    ({                                                                                                           \
        const rf b_ = (base) + RAY_CVF(m) * (step);                                                              \
        const rf den_ = (E) - b_ * (F);                                                                          \
        const rf t_ = (b_ * (A) - (C)) / den_;                                                                   \
        ((s) * den_ > 0.0f) ? t_ : (rf)(INFINITY);                                                               \
    })

RAY_INLINE rf cross_u(const Rays* r, const ri m) { return RAY_CROSSING(r->u0, r->du, r->oz, r->ox, r->dx, r->dz, r->su, m); }
RAY_INLINE rf cross_v(const Rays* r, const ri m) { return RAY_CROSSING(r->v0, r->dv, r->oz, r->oy, r->dy, r->dz, r->sv, m); }
RAY_INLINE rf cross_z(const Rays* r, const ri m) { return RAY_CROSSING(r->zn, r->dzc, 1.0f, r->oz, r->dz, 0.0f, r->sz, m); }

#if RAY_W == 1
/* cross_u / cross_v / cross_z for family f: the coefficients are picked first, so that one division is done. */
RAY_INLINE float cross_f(const Rays* r, const int f, const int m)
{
    const float base = f == FAMILY_U ? r->u0 : (f == FAMILY_V ? r->v0 : r->zn);
    const float step = f == FAMILY_U ? r->du : (f == FAMILY_V ? r->dv : r->dzc);
    const float A = f == FAMILY_Z ? 1.0f : r->oz;
    const float C = f == FAMILY_U ? r->ox : (f == FAMILY_V ? r->oy : r->oz);
    const float E = f == FAMILY_U ? r->dx : (f == FAMILY_V ? r->dy : r->dz);
    const float F = f == FAMILY_Z ? 0.0f : r->dz;
    const float s = f == FAMILY_U ? r->su : (f == FAMILY_V ? r->sv : r->sz);
    return RAY_CROSSING(base, step, A, C, E, F, s, m);
}
#endif

/* True when any lane of a mask is set (vectors: an or-reduction; PoCL's any() reduces lane by lane). */
#if RAY_W == 1
RAY_INLINE int ray_any(const ri m) { return m != 0; }
#elif RAY_W == 8
RAY_INLINE int ray_any(const ri m)
{
    const int4 b = m.lo | m.hi;
    const int2 c = b.lo | b.hi;
    return (c.x | c.y) < 0;
}
#else
RAY_INLINE int ray_any(const ri m)
{
    const int8 a = m.lo | m.hi;
    const int4 b = a.lo | a.hi;
    const int2 c = b.lo | b.hi;
    return (c.x | c.y) < 0;
}
#endif

/*
 * Steps 0 and 1 for the rays through pixels (x, y) (pixel coordinates as rf): fills r's direction, origin and grid
 * constants (not its signs: rays_entry() sets them), the clip interval [t_lo, t_hi) and the entry plane (0..5:
 * left, right, top, bottom, near, far; -1 when the camera is inside the frustum). Returns the mask of rays that
 * enter the frustum; the other outputs of a ray that misses are unspecified.
 */
RAY_INLINE ri rays_clip(const rf x, const rf y, const float8 g, const float16 c, Rays* r, rf* t_lo_out,
                        rf* t_hi_out, ri* plane_out)
{
    const rf px = (x + 0.5f - c.s2) / c.s0;
    const rf py = (y + 0.5f - c.s3) / c.s1;
    const rf dx = c.s4 * px + c.s5 * py + c.s6;
    const rf dy = c.s7 * px + c.s8 * py + c.s9;
    const rf dz = c.sa * px + c.sb * py + c.sc;
    const float ox = c.sd, oy = c.se, oz = c.sf;
    const float u0 = g.s0, v0 = g.s1, zn = g.s4, zf = g.s6;
    const float uw = -u0, vh = -v0;
    r->dx = dx;
    r->dy = dy;
    r->dz = dz;
    r->ox = ox;
    r->oy = oy;
    r->oz = oz;
    r->u0 = u0;
    r->v0 = v0;
    r->du = g.s2;
    r->dv = g.s3;
    r->zn = zn;
    r->dzc = g.s5;
    *t_lo_out = 0.0f;
    *t_hi_out = 0.0f;
    *plane_out = -1;

    /* Cyrus-Beck: a = n . d, b = n . o + c for left, right, top, bottom, near, far; candidates t = -b / a. */
    const rf a0 = dx - u0 * dz, a1 = -dx + uw * dz, a2 = dy - v0 * dz, a3 = -dy + vh * dz, a4 = dz, a5 = -dz;
    const float b0 = ox - u0 * oz, b1 = -ox + uw * oz, b2 = oy - v0 * oz, b3 = -oy + vh * oz, b4 = oz - zn,
                b5 = -oz + zf;
    /* Every ray misses when one half-space holds neither the origin (b < 0) nor any direction into it (a <= 0 for
     * all of them): the divisions below would give each a == 0 with b < 0, or t_hi < 0. */
#define RAY_OUTSIDE(A, B) ((B) < 0.0f && !ray_any(((A) <= 0.0f) == 0))
    if (RAY_OUTSIDE(a0, b0) || RAY_OUTSIDE(a1, b1) || RAY_OUTSIDE(a2, b2) || RAY_OUTSIDE(a3, b3) ||
        RAY_OUTSIDE(a4, b4) || RAY_OUTSIDE(a5, b5))
        return (ri)(0);
#undef RAY_OUTSIDE
    rf t_lo = 0.0f, t_hi = INFINITY;
    ri plane = -1;
    ri ok = (ri)(1) == (ri)(1);
#define RAY_CLIP(P, A, B)                                                                                          \
    {                                                                                                            \
        const rf t_ = -(B) / (A);                                                                                \
        if ((B) < 0.0f) ok &= ((A) != 0.0f);                                                                     \
        const ri raise_ = ((A) > 0.0f) & (t_ > t_lo);                                                            \
        plane = raise_ ? (ri)(P) : plane;                                                                        \
        t_lo = raise_ ? t_ : t_lo;                                                                               \
        t_hi = (((A) < 0.0f) & (t_ < t_hi)) ? t_ : t_hi;                                                         \
    }
    RAY_CLIP(0, a0, b0)
    RAY_CLIP(1, a1, b1)
    RAY_CLIP(2, a2, b2)
    RAY_CLIP(3, a3, b3)
    RAY_CLIP(4, a4, b4)
    RAY_CLIP(5, a5, b5)
#undef RAY_CLIP
    *t_lo_out = t_lo;
    *t_hi_out = t_hi;
    *plane_out = plane;
    return ok & (t_lo < t_hi);
}

/*
 * Steps 2 and 3 after rays_clip(): the entry cell at t_lo (clamped; the entry plane's own family set exactly) and
 * the step signs (into r).
 */
RAY_INLINE void rays_entry(Rays* r, const rf t_lo, const ri plane, const int4 n, ri* iu, ri* iv, ri* iz)
{
    const rf ex = r->ox + t_lo * r->dx, ey = r->oy + t_lo * r->dy, ez = r->oz + t_lo * r->dz;
    const ri i = ray_clamp_floor((ex / ez - r->u0) / r->du, n.x - 1);
    const ri j = ray_clamp_floor((ey / ez - r->v0) / r->dv, n.y - 1);
    const ri k = ray_clamp_floor((ez - r->zn) / r->dzc, n.z - 1);
    *iu = (plane == 0) ? (ri)(0) : ((plane == 1) ? (ri)(n.x - 1) : i);
    *iv = (plane == 2) ? (ri)(0) : ((plane == 3) ? (ri)(n.y - 1) : j);
    *iz = (plane == 4) ? (ri)(0) : ((plane == 5) ? (ri)(n.z - 1) : k);
    r->su = ray_sign(r->dx * r->oz - r->dz * r->ox);
    r->sv = ray_sign(r->dy * r->oz - r->dz * r->oy);
    r->sz = ray_sign(r->dz);
}

/* Steps 0-3: rays_clip() then rays_entry(). Returns the mask of rays that enter the frustum. */
RAY_INLINE ri rays_setup(const rf x, const rf y, const float8 g, const float16 c, const int4 n, Rays* r,
                         rf* t_lo, rf* t_hi, ri* plane, ri* iu, ri* iv, ri* iz)
{
    const ri enter = rays_clip(x, y, g, c, r, t_lo, t_hi, plane);
    rays_entry(r, *t_lo, *plane, n, iu, iv, iz);
    return enter;
}
