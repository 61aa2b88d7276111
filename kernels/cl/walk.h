/*
 * walk.h: the first-hit walk of kernels/traversal.py for a tile of TILE x TILE_H pixels (TILE_H = LANES / TILE),
 * one ray per lane of floatN / intN (N = LANES: 16 where the compiler targets AVX-512, else 8), with exact
 * empty-space skipping by jumps out of empty boxes. Shared by first_hit.cl (which writes each pixel's hit) and
 * shell.cl (which marks the hit cells). The ray set-up and crossings come from ray.h.
 *
 * The walk keeps each ray in exactly the plain loop's state (traversal.py step 5): its cell (i, j, k), the depth
 * t_entry where it entered the cell and the family it entered through. Each iteration, per ray:
 *   - the cell's group (2 x 2 x 2 cells) has chessboard distance d to the nearest group holding an occupied cell
 *     (the field of occupancy.cl, capped; 0: the group holds one);
 *   - d = 0: if the cell is occupied (the group's mask in the field says), it is the hit; else the box to leave is
 *     the cell itself (a plain step);
 *   - d > 0: the box to leave is the cube of groups of radius d - 1 around the cell's group, all empty, clipped to
 *     the grid;
 *   - the ray leaves the box where the first of its three families crosses the box's far boundary (t_x, ties
 *     u, v, z as the plain loop): a miss if t_x >= t_hi or the family leaves the grid, else that family enters
 *     the next cell, and every other family is put where the plain loop has it at that moment: past each of its
 *     boundaries crossed before t_x (at t_x too for families before the exit family in the tie order, which the
 *     plain loop steps first). In a box of one group (d = 1) that is one crossing per family, the group's middle
 *     boundary; in a larger box the cell is estimated from the exit point and then verified against the family's
 *     crossings (the boundary behind passed, the one ahead not), so it is the plain loop's cell whenever a
 *     family's crossings are monotone in their index, as the plain loop and traversal.py's skipping assume.
 * Every cell the plain loop visits inside the box is empty, so the first occupied cell, its entry depth and its
 * entry face are the plain loop's, bit for bit.
 *
 * Build options (-D, from kernels/cl/occupancy.py): those of ray.h, LANES (8 or 16: rays per work-item, the
 * device's native vector width, runtime.py's probe), TILE (4: the lane layout below), GROUP_LOG, WIDE_INDEX (1 when
 * a volume has 2^31 cells or more: cell offsets in 64 bits).
 *
 * Layouts:
 *   field  ushort (GD, gd.y, gd.x): this batch item's field, d << 8 | mask per group, gd = (row length, rows per
 *          slice, slices) (rows and slices padded; see occupancy.cl)
 */
#define RAY_W LANES
#include "ray.h"

#if TILE != 4
#error "walk.h lays a tile's rays out 4 pixels wide: TILE must be 4"
#endif
#define TILE_H (LANES / TILE)
#if LANES == 16
#define WALK_LX ((ri)(0, 1, 2, 3, 0, 1, 2, 3, 0, 1, 2, 3, 0, 1, 2, 3))
#define WALK_LY ((ri)(0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2, 3, 3, 3, 3))
#define WALK_LANES(G) G(s0) G(s1) G(s2) G(s3) G(s4) G(s5) G(s6) G(s7) G(s8) G(s9) G(sa) G(sb) G(sc) G(sd) G(se) G(sf)
typedef long16 rl;
#define RAY_CVL convert_long16
#elif LANES == 8
#define WALK_LX ((ri)(0, 1, 2, 3, 0, 1, 2, 3))
#define WALK_LY ((ri)(0, 0, 0, 0, 1, 1, 1, 1))
#define WALK_LANES(G) G(s0) G(s1) G(s2) G(s3) G(s4) G(s5) G(s6) G(s7)
typedef long8 rl;
#define RAY_CVL convert_long8
#else
#error "LANES must be 8 or 16"
#endif
#if GROUP_LOG != 1
#error "walk.h reads the field of 2 x 2 x 2 groups: GROUP_LOG must be 1"
#endif
#define GL GROUP_LOG

#if WIDE_INDEX
typedef rl cell_v;
#define CELL_CV RAY_CVL
#else
typedef ri cell_v;
#define CELL_CV
#endif

/* Entry codes: the family (0, 1, 2) of the step into the cell; ENTRY_PLANE + the clip plane (0..5) when the ray is
 * still in the cell where it entered the frustum; ENTRY_INSIDE when the camera is inside the frustum and the ray has
 * not stepped yet. */
#define ENTRY_INSIDE (-1)
#define ENTRY_PLANE 3

/* The flat cell index of (i, j, k) in a (D, H, W) volume. */
RAY_INLINE cell_v walk_cell(const ri i, const ri j, const ri k, const int4 n)
{
    return (CELL_CV(k) * n.y + CELL_CV(j)) * n.x + CELL_CV(i);
}

typedef struct {
    Rays r;      /* the tile's rays */
    ri hit;      /* mask of the rays that hit */
    ri i, j, k;  /* the hit cell */
    rf t_entry;  /* its entry depth */
    ri entry;    /* its entry code */
} TileHits;

/*
 * The first hits of the tile of pixels x0 .. x0 + 3, y0 .. y0 + TILE_H - 1 (pixels past w, h are misses): th->hit
 * and, for the rays that hit, the rest of th. Returns 0 when no ray of the tile enters the frustum (th->hit all clear).
 * max_iter bounds the walk (every iteration moves one family at least a cell on).
 */
RAY_INLINE int trace_tile(const int x0, const int y0, const int w, const int h, __global const ushort* field,
                          const int4 gd, const float8 g, const float16 c, const int4 n, const int max_iter,
                          TileHits* th)
{
    const ri xs = x0 + WALK_LX, ys = y0 + WALK_LY;
    Rays r;
    rf t_lo, t_hi;
    ri plane, iu = 0, iv = 0, iz = 0;
    ri active = rays_clip(RAY_CVF(xs), RAY_CVF(ys), g, c, &r, &t_lo, &t_hi, &plane) & (xs < w) & (ys < h);
    th->hit = 0;
    th->i = th->j = th->k = 0;
    th->t_entry = t_lo;
    th->entry = ENTRY_INSIDE;
    if (!ray_any(active)) {
        th->r = r;
        return 0;
    }
    rays_entry(&r, t_lo, plane, n, &iu, &iv, &iz);
    th->r = r;

    const ri su = RAY_CVI(r.su), sv = RAY_CVI(r.sv), sz = RAY_CVI(r.sz);
    const ri fwu = su > 0, fwv = sv > 0, fwz = sz > 0; /* masks: the boundary ahead of cell m is m + 1 */
    const ri pu = -fwu, pv = -fwv, pz = -fwz;         /* that + 1 as 0 / 1 */
    const float inv_du = 1.0f / r.du, inv_dv = 1.0f / r.dv, inv_dz = 1.0f / r.dzc; /* for estimates only */
    rf t_entry = t_lo;
    ri entry = (plane >= 0) ? ENTRY_PLANE + plane : (ri)(ENTRY_INSIDE);
    ri hit = 0;

    for (int it = 0; it < max_iter; ++it) {
        if (!ray_any(active)) break;
        /* The cell's group in the field: its distance d and its mask, where the cell's bit says if it is occupied. */
        const ri goff = ((iz >> 1) * gd.y + (iv >> 1)) * gd.x + (iu >> 1);
        ri f;
#define G(l) f.l = field[(uint)goff.l];
        WALK_LANES(G)
#undef G
        const ri d = f >> 8;
        const ri h0 = active & (((f >> ((iu & 1) | ((iv & 1) << 1) | ((iz & 1) << 2))) & 1) != 0);
        hit |= h0;
        active &= ~h0;

        /* The box to leave: the cell (d = 0) or the cube of groups of radius d - 1; its far boundary per family. */
        const ri big = d > 0;
        const ri rad = (d - 1) << GL;
        const ri eu = fwu ? min(big ? (((iu >> GL) + 1) << GL) + rad : iu + 1, n.x)
                          : max(big ? ((iu >> GL) << GL) - rad : iu, 0);
        const ri ev = fwv ? min(big ? (((iv >> GL) + 1) << GL) + rad : iv + 1, n.y)
                          : max(big ? ((iv >> GL) << GL) - rad : iv, 0);
        const ri ez = fwz ? min(big ? (((iz >> GL) + 1) << GL) + rad : iz + 1, n.z)
                          : max(big ? ((iz >> GL) << GL) - rad : iz, 0);
        const rf teu = cross_u(&r, eu), tev = cross_v(&r, ev), tez = cross_z(&r, ez);
        const ri xu = (teu <= tev) & (teu <= tez); /* the exit family, ties u, v, z */
        const ri xv = ~xu & (tev <= tez);
        const ri xz = ~xu & ~xv;
        const rf tx = xu ? teu : (xv ? tev : tez);
        /* The exit family enters the next cell; leaving the frustum (t_hi) or the grid is a miss. */
        ri cu = xu ? (fwu ? eu : eu - 1) : iu;
        ri cv = xv ? (fwv ? ev : ev - 1) : iv;
        ri cz = xz ? (fwz ? ez : ez - 1) : iz;
        const ri go = active & (tx < t_hi) & (cu >= 0) & (cu < n.x) & (cv >= 0) & (cv < n.y) & (cz >= 0) &
                      (cz < n.z);
        active = go;
        const ri jump = go & big;
        if (ray_any(jump) && !ray_any(jump & (d > 1))) {
            /* Every jump leaves the cell's own group (d = 1): another family has at most the group's middle
             * boundary, the one ahead of the cell, before t_x (its far boundary is not passed: that family did not
             * exit), so one crossing each puts it in place. */
            const ri tie_u = xv | xz, tie_v = xz; /* families before the exit family in the tie order */
            const rf au_ = cross_u(&r, iu + pu), av_ = cross_v(&r, iv + pv), az_ = cross_z(&r, iz + pz);
            cu = (jump & ~xu & (tie_u ? (au_ <= tx) : (au_ < tx))) ? iu + su : cu;
            cv = (jump & ~xv & (tie_v ? (av_ <= tx) : (av_ < tx))) ? iv + sv : cv;
            cz = (jump & ~xz & (az_ < tx)) ? iz + sz : cz;
        } else if (ray_any(jump)) {
            /* The other families' cells at t_x: estimated from the exit point, kept between the current cell and
             * the box's last one, then verified. */
            const rf qx = r.ox + tx * r.dx, qy = r.oy + tx * r.dy, qz = r.oz + tx * r.dz;
            const rf iq = 1.0f / qz;
            ri au = ray_clamp_floor((qx * iq - r.u0) * inv_du, n.x - 1);
            ri av = ray_clamp_floor((qy * iq - r.v0) * inv_dv, n.y - 1);
            ri az = ray_clamp_floor((qz - r.zn) * inv_dz, n.z - 1);
            au = fwu ? clamp(au, iu, eu - 1) : clamp(au, eu, iu);
            av = fwv ? clamp(av, iv, ev - 1) : clamp(av, ev, iv);
            az = fwz ? clamp(az, iz, ez - 1) : clamp(az, ez, iz);
            const ri mu = jump & ~xu & (su != 0), mv = jump & ~xv & (sv != 0), mz = jump & ~xz & (sz != 0);
            cu = mu ? au : cu;
            cv = mv ? av : cv;
            cz = mz ? az : cz;
            const ri tie_u = xv | xz, tie_v = xz; /* families before the exit family in the tie order */
            for (;;) {
                const rf au_ = cross_u(&r, cu + pu), av_ = cross_v(&r, cv + pv), az_ = cross_z(&r, cz + pz);
                const rf bu_ = cross_u(&r, cu + 1 - pu), bv_ = cross_v(&r, cv + 1 - pv), bz_ = cross_z(&r, cz + 1 - pz);
                /* the boundary ahead already passed: one cell on; the one behind not yet passed: one cell back */
                const ri onu = mu & (tie_u ? (au_ <= tx) : (au_ < tx));
                const ri onv = mv & (tie_v ? (av_ <= tx) : (av_ < tx));
                const ri onz = mz & (az_ < tx);
                const ri backu = mu & (cu != iu) & ~(tie_u ? (bu_ <= tx) : (bu_ < tx));
                const ri backv = mv & (cv != iv) & ~(tie_v ? (bv_ <= tx) : (bv_ < tx));
                const ri backz = mz & (cz != iz) & ~(bz_ < tx);
                if (!ray_any(onu | onv | onz | backu | backv | backz)) break;
                cu += (onu & su) - (backu & su);
                cv += (onv & sv) - (backv & sv);
                cz += (onz & sz) - (backz & sz);
            }
        }
        iu = go ? cu : iu;
        iv = go ? cv : iv;
        iz = go ? cz : iz;
        t_entry = go ? tx : t_entry;
        entry = go ? (xu ? (ri)(0) : (xv ? (ri)(1) : (ri)(2))) : entry;
    }
    th->hit = hit;
    th->i = iu;
    th->j = iv;
    th->k = iz;
    th->t_entry = t_entry;
    th->entry = entry;
    return 1;
}
