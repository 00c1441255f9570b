/* The collision decisions of the IK's and the planner's checks in one call (included by _native.c once per
 * real type, like _native_solve.c): whether every checked capsule pair and every capsule against every world
 * object (round ones: spheres, capsules, points as segments with a radius; half-spaces; boxes; cylinders
 * against the sphere geoms) has d - margin >= slack, per configuration. diffkin/collision/robot.py
 * (RobotCollision._clear) places the capsules and calls it; cylinders against proper segments stay with the
 * torch broad phase. Each configuration may have its own world (wid: one scene per planning problem, the
 * object arrays stacked by diffkin.collision.World.stack); a block gathers its lanes' objects once per
 * object.
 *
 * Capsules are given component-major as the placement product leaves them: A and B (G x 3 x N) the segment
 * ends, r (G) the radii. The distance of two segments is Ericson's closest points of two segments
 * (Real-Time Collision Detection, 5.1.9) written without branches, so that the loop over the configurations
 * of a block can vectorise (GCC 12 keeps it scalar: under the default -ftrapping-math a select on a double
 * comparison stays a branch; -fno-trapping-math for the whole library changed other kernels' results); the
 * planner's hot loops (the spheres against boxes and cylinders, the lanes' bounding boxes, the culls against
 * an object) are written four lanes at a time as vectors (DK(v4)) instead; degenerate segments (points) take
 * the clamped formulas. The test compares squared
 * centre distances with (r_a + r_b + margin + slack)^2: no square root. Configurations run in blocks of
 * COLLIDE_BLOCK (the block's capsules stay in cache while every pair is tested), blocks shared between
 * threads.
 */
#ifndef DK_COLLIDE_ONCE
#define DK_COLLIDE_ONCE
#define COLLIDE_BLOCK 256
#define CULL_GEOMS 512 /* blocks of models with more geoms test every entry */
#define CULL_GROUP 8   /* geoms per group where the caller names none (collide_runs_init) */
/* What a caller reads of a block's decisions (DK(collide_lanes)): every lane; the lanes up to the first
 * colliding one; or only whether some lane collides. */
#define COLLIDE_ALL 0
#define COLLIDE_FIRST 1
#define COLLIDE_ANY 2
/* COLLIDE_ANY, and each lane's decision at a second, larger threshold as well (a cover: the planner's sample
 * clear of it proves its neighbours, _native_plan.c): the culls at the larger one, the block stopping at the
 * first collision at the smaller one only */
#define COLLIDE_COVER 3
#define COLLIDE_NARROW 4 /* the lanes of DK(collide_any_narrow) */

/* A collision a caller's COLLIDE_ANY or COLLIDE_COVER decisions found between a sphere geom and a box or a
 * cylinder: decided first next time (DK(collide_hint)), before the broad phase. Consecutive samples of a search
 * tend to meet the same object with the same sphere: about 92 % of the planner's first blocks of an edge stop
 * at a box, 1-10 % at a cylinder. */
typedef struct {
    int64_t w, g, cyl; /* the object (w < 0: none), the geom, and whether the object is a cylinder */
} CollideHint;

/* `for (int l = 0; l < m; l++) { body }` as a reduction over the lanes: an omp simd loop with the reduction
 * clauses from SIMD_REDUCE_LANES lanes on, a plain loop below. GCC lowers an omp simd reduction to an array of
 * per-lane partial results on the stack, stored as one vector and combined one by one (narrow loads of a wide
 * store: a stall each), which costs more than a few lanes' work (the nearest-node scan of _native_plan.c; the
 * planner's decisions took 30 % less time with the plain loop below 16 lanes, before their lanes' boxes went
 * to DK(rows_range)). min and max are exact in any order. */
#define SIMD_REDUCE_LANES 16
#define REDUCE_LANES(m, clauses, ...)                                                                             \
    do {                                                                                                         \
        if ((m) < SIMD_REDUCE_LANES) {                                                                           \
            for (int l = 0; l < (m); l++) { __VA_ARGS__ }                                                        \
        } else {                                                                                                 \
            _Pragma(clauses) for (int l = 0; l < (m); l++) { __VA_ARGS__ }                                       \
        }                                                                                                        \
    } while (0)

/* The groups of a model's geoms for the broad phase's level above the geoms (VAMP's per-link bounding
 * spheres, as boxes): runs of consecutive geoms (a link's: the planner groups by frame; runs of CULL_GROUP
 * otherwise), and the self pairs ordered by the pair of their groups, so that a pair of groups found apart
 * skips all its pairs at once (a Panda's 690 pairs fall into about 40 pairs of links, most of them apart in
 * most configurations). Type-free; built once per call (per thread in the planner). */
typedef struct {
    int64_t NG;                      /* groups (0: no culling: more than CULL_GEOMS geoms, or out of memory) */
    int64_t start[CULL_GEOMS + 1];   /* group u: geoms start[u] .. start[u + 1] - 1 */
    int32_t of[CULL_GEOMS];          /* the group of each geom */
    int64_t *pi, *pj, *end;          /* [P] the pairs ordered by group pair; end[p]: one past p's run */
} CollideRuns;

/* Runs for the G geoms and P pairs (pi, pj) of a call: the group of geom g is key[g]'s run of equal
 * consecutive values (key NULL: runs of CULL_GROUP); the pairs counting-sorted by (group of i, group of j),
 * stable. Returns 0 when memory ran out (then NG is 0: every pair on its own, in the caller's order). Free
 * with collide_runs_free. */
static int collide_runs_init(CollideRuns *R, int64_t G, int64_t P, const int64_t *pi, const int64_t *pj,
                             const int64_t *key) {
    R->NG = 0;
    R->pi = R->pj = R->end = NULL;
    if (G > CULL_GEOMS || G <= 0) return 1;
    int64_t NG = 0;
    for (int64_t g = 0; g < G; g++) {
        if (g == 0 || (key ? key[g] != key[g - 1] : g % CULL_GROUP == 0)) R->start[NG++] = g;
        R->of[g] = (int32_t)(NG - 1);
    }
    R->start[NG] = G;
    int64_t *count = (int64_t *)calloc((size_t)(NG * NG + 1), sizeof(int64_t));
    R->pi = (int64_t *)malloc(sizeof(int64_t) * (size_t)(P > 0 ? P : 1));
    R->pj = (int64_t *)malloc(sizeof(int64_t) * (size_t)(P > 0 ? P : 1));
    R->end = (int64_t *)malloc(sizeof(int64_t) * (size_t)(P > 0 ? P : 1));
    if (!(count && R->pi && R->pj && R->end)) {
        free(count), free(R->pi), free(R->pj), free(R->end);
        R->pi = R->pj = R->end = NULL;
        return 0;
    }
    for (int64_t p = 0; p < P; p++) count[R->of[pi[p]] * NG + R->of[pj[p]] + 1]++;
    for (int64_t k = 0; k < NG * NG; k++) count[k + 1] += count[k]; /* count[k]: where bucket k starts */
    for (int64_t p = 0; p < P; p++) {
        const int64_t k = R->of[pi[p]] * NG + R->of[pj[p]], at = count[k]++;
        R->pi[at] = pi[p], R->pj[at] = pj[p];
    }
    for (int64_t p = P - 1; p >= 0; p--) /* count[k] is now where bucket k ends */
        R->end[p] = count[R->of[R->pi[p]] * NG + R->of[R->pj[p]]];
    free(count);
    R->NG = NG;
    return 1;
}

static void collide_runs_free(CollideRuns *R) {
    free(R->pi), free(R->pj), free(R->end);
    R->pi = R->pj = R->end = NULL;
    R->NG = 0;
}
#endif

/* Ericson's closest points of the segments p + s u and q + t v (s, t in [0, 1]; w = p - q) without
 * branches: every division runs on a safe denominator and a select picks the case. Writes s and t and
 * returns the squared distance. Inlined where it is used: in the lane loop of DK(segments_d2) and in the
 * differential-IK step's collision rows (_native_velocity.c), which take the closest points of one pair. */
static inline __attribute__((always_inline)) real DK(segment_closest)(real ux, real uy, real uz, real vx, real vy,
                                                                    real vz, real wx, real wy, real wz,
                                                                    real *s_out, real *t_out) {
    const real eps = (real)1e-12;
    real a = ux * ux + uy * uy + uz * uz, e = vx * vx + vy * vy + vz * vz, b = ux * vx + uy * vy + uz * vz;
    real c = ux * wx + uy * wy + uz * wz, f = vx * wx + vy * wy + vz * wz;
    real den = a * e - b * b;
    const int pa_ = a > eps, pe_ = e > eps, pd_ = (den > eps * a * e) & (den > 0);
    real ai = 1 / (pa_ ? a : 1), ei = 1 / (pe_ ? e : 1), s = (b * f - c * e) / (pd_ ? den : 1);
    ai = pa_ ? ai : 0;
    ei = pe_ ? ei : 0;
    s = pd_ ? s : 0;
    s = s < 0 ? 0 : (s > 1 ? 1 : s);
    real t = (b * s + f) * ei;
    real tc = t < 0 ? 0 : (t > 1 ? 1 : t);
    real s2 = (b * tc - c) * ai; /* t clamped: s again for the clamped t */
    s2 = s2 < 0 ? 0 : (s2 > 1 ? 1 : s2);
    s = t != tc ? s2 : s;
    const real sp0 = -c * ai; /* the second segment a point: t = 0, s = clamp(-c / a) */
    s = pe_ ? s : (sp0 < 0 ? 0 : (sp0 > 1 ? 1 : sp0));
    s = pa_ ? s : 0; /* the first a point: s = 0 (t = clamp(f / e) above) */
    t = pe_ ? tc : 0;
    real dx = wx + s * ux - t * vx, dy = wy + s * uy - t * vy, dz = wz + s * uz - t * vz;
    *s_out = s;
    *t_out = t;
    return dx * dx + dy * dy + dz * dz;
}

/* Squared distance between the segments from p to u_end and from q to v_end, lanes 0 .. m-1 of component
 * arrays (sp, sq: the strides between the x, y, z components), into d2. */
static void DK(segments_d2)(const real *p, const real *u_end, int64_t sp, const real *q, const real *v_end,
                            int64_t sq, int m, real *restrict d2) {
    for (int l = 0; l < m; l++) {
        real ux = u_end[l] - p[l], uy = u_end[sp + l] - p[sp + l], uz = u_end[2 * sp + l] - p[2 * sp + l];
        real vx = v_end[l] - q[l], vy = v_end[sq + l] - q[sq + l], vz = v_end[2 * sq + l] - q[2 * sq + l];
        real wx = p[l] - q[l], wy = p[sp + l] - q[sq + l], wz = p[2 * sp + l] - q[2 * sq + l];
        real s, t;
        d2[l] = DK(segment_closest)(ux, uy, uz, vx, vy, vz, wx, wy, wz, &s, &t);
    }
}

/* The world of lane l of the block at n0 (0 without per-configuration worlds). */
#define WORLD_OF(c, n0, l) ((c)->wid ? (c)->wid[(n0) + (l)] : 0)

/* Whether the box-frame segment p + s d (s in [0, 1]) meets the closed box |x_k| <= h_k (the slab test,
 * branch-free: a direction component ~0 keeps the whole parameter range when |p_k| <= h_k, none otherwise).
 * Closed: a segment through a flat box (some h_k = 0) penetrates it (a positive depth). */
static inline __attribute__((always_inline)) int DK(box_segment_meets)(const real p[3], const real d[3],
                                                                     const real h[3]) {
    real lo = 0, hi = 1;
    int inside = 1;
    for (int k = 0; k < 3; k++) {
        const real ad = d[k] < 0 ? -d[k] : d[k];
        const int par = ad < (real)1e-12;
        const real inv = 1 / (par ? 1 : d[k]);
        real t1 = (-h[k] - p[k]) * inv, t2 = (h[k] - p[k]) * inv;
        real tl = t1 < t2 ? t1 : t2, th = t1 < t2 ? t2 : t1;
        const real pk = p[k] < 0 ? -p[k] : p[k];
        inside &= par ? pk <= h[k] : 1;
        tl = par ? lo : tl;
        th = par ? hi : th;
        lo = tl > lo ? tl : lo;
        hi = th < hi ? th : hi;
    }
    return inside & (lo <= hi);
}

/* The world vector (x, y, z) in the frame of lane l's box (R: its rotation's entry (0, 0), the 9 entries
 * COLLIDE_BLOCK apart, row-major): R^T (x, y, z) into bx, by, bz. */
static inline __attribute__((always_inline)) void DK(box_frame)(const real *R, real x, real y, real z, real *bx,
                                                                real *by, real *bz) {
    const int64_t S = COLLIDE_BLOCK;
    *bx = x * R[0] + y * R[3 * S] + z * R[6 * S];
    *by = x * R[S] + y * R[4 * S] + z * R[7 * S];
    *bz = x * R[2 * S] + y * R[5 * S] + z * R[8 * S];
}

/* Four lanes of real as one vector (GCC's and clang's vector extensions: one AVX register of doubles, one SSE
 * register of floats, NEON's alike; elsewhere the compiler splits it): the 4-lane loops of the sphere-object
 * tests below, which GCC 12 left scalar with a branch per lane (its cost model refuses a constant trip count
 * of 4; the wide loops ran their last 1-7 lanes so); in the planner's search these tests took about 17 % of
 * the time. They pass only between static inline functions, so the ABI note GCC prints for them in a build
 * without AVX (-Wpsabi: a vector argument's ABI) does not apply; a pragma does not silence it in GCC 12, and
 * the library's build reads the compiler's messages only when it fails. */
typedef real DK(v4) __attribute__((vector_size(4 * sizeof(real))));
typedef __typeof__(((DK(v4)){0} < (DK(v4)){0})[0]) DK(v4_int); /* the integer of a comparison's lanes */
typedef DK(v4_int) DK(m4) __attribute__((vector_size(4 * sizeof(real)))); /* a comparison: 0 or all bits set */
#ifndef DK_LANES4_ONCE
#define DK_LANES4_ONCE
typedef uint8_t lanes4_u8 __attribute__((vector_size(4)));
/* lanes i, j, k, l of the 8 of a then b */
#if defined(__clang__)
#define DK_V4_SHUFFLE(a, b, i, j, k, l) __builtin_shufflevector(a, b, i, j, k, l)
#else
#define DK_V4_SHUFFLE(a, b, i, j, k, l) __builtin_shuffle(a, b, (DK(m4)){i, j, k, l})
#endif
#endif

static inline __attribute__((always_inline)) DK(v4) DK(v4_splat)(real x) { return (DK(v4)){x, x, x, x}; }

/* lanes l .. l + 3 of p (full) or, past m, lane m - 1 repeated (a block's last lanes: its results there are
 * dropped) */
static inline __attribute__((always_inline)) DK(v4) DK(v4_load)(const real *p, int l, int m, const int full) {
    DK(v4) v;
    if (full) memcpy(&v, p + l, sizeof v);
    else
        for (int i = 0; i < 4; i++) v[i] = p[l + i < m ? l + i : m - 1];
    return v;
}

/* the lanes of a where mask is set, of b elsewhere (C's ?: lane by lane) */
static inline __attribute__((always_inline)) DK(v4) DK(v4_select)(DK(m4) mask, DK(v4) a, DK(v4) b) {
    return (DK(v4))((mask & (DK(m4))a) | (~mask & (DK(m4))b));
}

/* a < b ? a : b and a > b ? a : b lane by lane (x86's min and max are exactly these: one instruction where a
 * select is two) */
static inline __attribute__((always_inline)) DK(v4) DK(v4_min)(DK(v4) a, DK(v4) b) {
#if defined(__AVX2__) && DK_TILE == 4
    return (DK(v4))_mm256_min_pd((__m256d)a, (__m256d)b);
#elif defined(__AVX2__) && DK_TILE == 8
    return (DK(v4))_mm_min_ps((__m128)a, (__m128)b);
#else
    return DK(v4_select)(a < b, a, b);
#endif
}

static inline __attribute__((always_inline)) DK(v4) DK(v4_max)(DK(v4) a, DK(v4) b) {
#if defined(__AVX2__) && DK_TILE == 4
    return (DK(v4))_mm256_max_pd((__m256d)a, (__m256d)b);
#elif defined(__AVX2__) && DK_TILE == 8
    return (DK(v4))_mm_max_ps((__m128)a, (__m128)b);
#else
    return DK(v4_select)(a > b, a, b);
#endif
}

/* |x| lane by lane, the sign bit cleared (x < 0 ? -x : x but for the sign of a zero, which no decision reads) */
static inline __attribute__((always_inline)) DK(v4) DK(v4_abs)(DK(v4) x) {
    return (DK(v4))((DK(m4))x & ~(DK(m4))DK(v4_splat)((real)-0.0));
}

static inline __attribute__((always_inline)) DK(v4) DK(v4_sqrt)(DK(v4) x) {
    DK(v4) r;
    for (int i = 0; i < 4; i++) r[i] = (real)sqrt((double)x[i]);
    return r;
}

/* flags[l + i] &= mask's lane i, for the lanes below m (full: all four) */
static inline __attribute__((always_inline)) void DK(v4_and_into)(uint8_t *restrict flags, int l, int m, DK(m4) mask,
                                                                const int full) {
    if (full) {
        lanes4_u8 f, bits = __builtin_convertvector(mask, lanes4_u8) & 1;
        memcpy(&f, flags + l, 4);
        f &= bits;
        memcpy(flags + l, &f, 4);
    } else
        for (int i = 0; i < 4 && l + i < m; i++) flags[l + i] &= (uint8_t)(mask[i] & 1);
}

/* Squared distance from the box-frame point (x, y, z) to the box |x_k| <= h_k (0 inside) and the largest
 * excess max_k (|x_k| - h_k) (< 0 inside: minus the depth), lane by lane. */
static inline __attribute__((always_inline)) DK(v4) DK(box_point_d2_v4)(DK(v4) x, DK(v4) y, DK(v4) z, DK(v4) hx,
                                                                      DK(v4) hy, DK(v4) hz, DK(v4) *excess) {
    const DK(v4) zero = DK(v4_splat)(0);
    DK(v4) ex = DK(v4_abs)(x) - hx, ey = DK(v4_abs)(y) - hy, ez = DK(v4_abs)(z) - hz;
    *excess = DK(v4_max)(DK(v4_max)(ex, ey), ez);
    ex = DK(v4_max)(ex, zero);
    ey = DK(v4_max)(ey, zero);
    ez = DK(v4_max)(ez, zero);
    return ex * ex + ey * ey + ez * ez;
}

/* DK(box_point_d2_v4) of one point (a segment's end: DK(box_lanes)) */
static inline __attribute__((always_inline)) real DK(box_point_d2)(real x, real y, real z, real hx, real hy,
                                                                 real hz, real *excess) {
    DK(v4) e;
    const DK(v4) d2 = DK(box_point_d2_v4)(DK(v4_splat)(x), DK(v4_splat)(y), DK(v4_splat)(z), DK(v4_splat)(hx),
                                          DK(v4_splat)(hy), DK(v4_splat)(hz), &e);
    *excess = e[0];
    return d2[0];
}

/* Axis-major boxes (axis k of box i at k CULL_GEOMS + i: DK(collide_lanes)'s geoms' and groups') -> box i's
 * bounds [blo, bhi] (3 each), as DK(aabb_apart) reads them */
static inline void DK(box_at)(const real *lo, const real *hi, int64_t i, real *blo, real *bhi) {
    for (int k = 0; k < 3; k++) blo[k] = lo[k * CULL_GEOMS + i], bhi[k] = hi[k * CULL_GEOMS + i];
}

/* One chunk of DK(rows_range): lanes l .. l + 3 (past m, lane m - 1 again: the same least and largest) */
static inline __attribute__((always_inline)) void DK(range_v4)(const real *a, const real *b, int l, int m,
        const int full, const int first, DK(v4) *lo, DK(v4) *hi, DK(v4) *sum) {
    const DK(v4) x = DK(v4_load)(a, l, m, full);
    DK(v4) y = x, z = x, s = x;
    if (b) { /* a segment's two ends */
        const DK(v4) v = DK(v4_load)(b, l, m, full);
        y = DK(v4_min)(x, v), z = DK(v4_max)(v, x), s = x + v;
    }
    *lo = first ? y : DK(v4_min)(y, *lo);
    *hi = first ? z : DK(v4_max)(z, *hi);
    *sum = first ? s : *sum + s;
}

/* Lane i of the result: op (0 min, 1 max, 2 sum) over the four lanes of r[i], for four vectors at once (two
 * rounds of shuffles: 6 shuffles and 3 ops where each vector alone takes 3 extractions and 3 ops) */
static inline __attribute__((always_inline)) DK(v4) DK(v4_op)(DK(v4) a, DK(v4) b, const int op) {
    return op == 0 ? DK(v4_min)(a, b) : op == 1 ? DK(v4_max)(a, b) : a + b;
}
static inline __attribute__((always_inline)) DK(v4) DK(v4_across)(const DK(v4) *r, const int op) {
    const DK(v4) m01 = DK(v4_op)(DK_V4_SHUFFLE(r[0], r[1], 0, 4, 2, 6), DK_V4_SHUFFLE(r[0], r[1], 1, 5, 3, 7), op);
    const DK(v4) m23 = DK(v4_op)(DK_V4_SHUFFLE(r[2], r[3], 0, 4, 2, 6), DK_V4_SHUFFLE(r[2], r[3], 1, 5, 3, 7), op);
    return DK(v4_op)(DK_V4_SHUFFLE(m01, m23, 0, 1, 4, 5), DK_V4_SHUFFLE(m01, m23, 2, 3, 6, 7), op);
}

/* The least and the largest of lanes 0 .. m - 1 (m >= 1) of each of the n rows of a (row i from i N; row
 * 3 g + k is geom g's axis k) and, where b is not NULL, of b's too (a segment's two ends), into lo and hi
 * axis-major (row 3 g + k's at k * CULL_GEOMS + g), and whether some lane of the row is NaN into nan[i] (min and max may drop a NaN, a sum keeps it; the sum, formed in any order, is only
 * asked that: an infinity's opposite, or an overflow meeting one, also makes it NaN, which loses a cull,
 * never a collision): four rows at a time, their lanes four at a time, the four rows' vectors reduced across
 * their lanes together (DK(v4_across)). */
static inline void DK(rows_range)(const real *a, const real *b, int64_t N, int64_t n, int m, real *restrict lo,
                                  real *restrict hi, uint8_t *restrict nan) {
    for (int64_t i = 0; i < n; i += 4) {
        DK(v4) L[4], H[4], S[4];
        for (int j = 0; j < 4; j++) {
            const int64_t row = i + j < n ? i + j : n - 1; /* past n the last row again */
            const real *ar = a + row * N, *br = b ? b + row * N : NULL;
            int l = 0;
            if (m >= 4) {
                DK(range_v4)(ar, br, 0, m, 1, 1, L + j, H + j, S + j);
                for (l = 4; l + 4 <= m; l += 4) DK(range_v4)(ar, br, l, m, 1, 0, L + j, H + j, S + j);
                if (l < m) DK(range_v4)(ar, br, l, m, 0, 0, L + j, H + j, S + j);
            } else
                DK(range_v4)(ar, br, 0, m, 0, 1, L + j, H + j, S + j);
        }
        const DK(v4) lo4 = DK(v4_across)(L, 0), hi4 = DK(v4_across)(H, 1), s4 = DK(v4_across)(S, 2);
        for (int j = 0; j < 4 && i + j < n; j++) {
            const int64_t at = ((i + j) % 3) * CULL_GEOMS + (i + j) / 3;
            lo[at] = lo4[j], hi[at] = hi4[j], nan[i + j] = s4[j] != s4[j];
        }
    }
}

/* Lanes l .. l + 3 (those below m) of DK(box_points_lanes). */
static inline __attribute__((always_inline)) void DK(box_points_v4)(const real *A, int64_t N, real rg,
        const real *bc, const real *bR, const real *bh, real thr, int l, int m, uint8_t *restrict clear,
        real thr_hi, uint8_t *restrict hi, const int shared, const int full) {
    /* entry k of the box of the lanes: gathered per lane (rows COLLIDE_BLOCK apart), or one box for every lane
     * (shared: the object's own 3, 9, 3 entries, no copy) */
#define BOX_ENTRY(p, k) (shared ? DK(v4_splat)((p)[k]) : DK(v4_load)((p) + (k) * COLLIDE_BLOCK, l, m, full))
    const DK(v4) zero = DK(v4_splat)(0);
    const DK(v4) dx = DK(v4_load)(A, l, m, full) - BOX_ENTRY(bc, 0), dy = DK(v4_load)(A + N, l, m, full) - BOX_ENTRY(bc, 1),
                 dz = DK(v4_load)(A + 2 * N, l, m, full) - BOX_ENTRY(bc, 2);
    /* R^T (dx, dy, dz), as DK(box_frame), written out */
    const DK(v4) px = dx * BOX_ENTRY(bR, 0) + dy * BOX_ENTRY(bR, 3) + dz * BOX_ENTRY(bR, 6);
    const DK(v4) py = dx * BOX_ENTRY(bR, 1) + dy * BOX_ENTRY(bR, 4) + dz * BOX_ENTRY(bR, 7);
    const DK(v4) pz = dx * BOX_ENTRY(bR, 2) + dy * BOX_ENTRY(bR, 5) + dz * BOX_ENTRY(bR, 8);
    DK(v4) excess;
    const DK(v4) best = DK(box_point_d2_v4)(px, py, pz, BOX_ENTRY(bh, 0), BOX_ENTRY(bh, 1), BOX_ENTRY(bh, 2), &excess);
#undef BOX_ENTRY
    const DK(v4) d = DK(v4_select)(best > zero, DK(v4_sqrt)(best), excess);
    DK(v4_and_into)(clear, l, m, d >= DK(v4_splat)(rg + thr), full);
    if (hi) DK(v4_and_into)(hi, l, m, d >= DK(v4_splat)(rg + thr_hi), full); /* hi: NULL or not in each inlined
                                                                                 * copy, no test left */
}

/* DK(box_lanes) of sphere geoms (point): the signed distance of the centre, outside its distance, inside minus
 * the depth, four lanes at a time (DK(box_points_v4)). */
static inline __attribute__((always_inline)) void DK(box_points_lanes)(const real *A, int64_t N, real rg,
        const real *bc, const real *bR, const real *bh, real thr, int m, uint8_t *restrict clear, real thr_hi,
        uint8_t *restrict hi, const int shared) {
    int l = 0;
    for (; l + 4 <= m; l += 4) DK(box_points_v4)(A, N, rg, bc, bR, bh, thr, l, m, clear, thr_hi, hi, shared, 1);
    if (l < m) DK(box_points_v4)(A, N, rg, bc, bR, bh, thr, l, m, clear, thr_hi, hi, shared, 0);
}

static void DK(box_points)(const real *A, int64_t N, real rg,
        const real *bc, const real *bR, const real *bh, real thr, int m, uint8_t *restrict clear) {
    DK(box_points_lanes)(A, N, rg, bc, bR, bh, thr, m, clear, 0, NULL, 0);
}

/* DK(box_points) of COLLIDE_NARROW lanes (a constant trip count) */
static void DK(box_points_narrow)(const real *A, int64_t N, real rg,
        const real *bc, const real *bR, const real *bh, real thr, uint8_t *restrict clear) {
    DK(box_points_lanes)(A, N, rg, bc, bR, bh, thr, COLLIDE_NARROW, clear, 0, NULL, 0);
}

/* DK(box_points) deciding each lane at thr_hi as well, into hi (&=) */
static void DK(box_points_cover)(const real *A, int64_t N, real rg,
        const real *bc, const real *bR, const real *bh, real thr, int m, uint8_t *restrict clear, real thr_hi,
        uint8_t *restrict hi) {
    DK(box_points_lanes)(A, N, rg, bc, bR, bh, thr, m, clear, thr_hi, hi, 0);
}

/* DK(box_points) and DK(box_points_cover) (hi not NULL), of any m and of COLLIDE_NARROW lanes, of one box for
 * every lane (the object's own centre bc[3], rotation bR[9] and half extents bh[3]: a block in one world
 * row, nothing gathered) */
static void DK(box_points_one)(const real *A, int64_t N, real rg,
        const real *bc, const real *bR, const real *bh, real thr, int m, uint8_t *restrict clear, real thr_hi,
        uint8_t *restrict hi) {
    if (hi) DK(box_points_lanes)(A, N, rg, bc, bR, bh, thr, m, clear, thr_hi, hi, 1);
    else DK(box_points_lanes)(A, N, rg, bc, bR, bh, thr, m, clear, 0, NULL, 1);
}

static void DK(box_points_one_narrow)(const real *A, int64_t N,
        real rg, const real *bc, const real *bR, const real *bh, real thr, uint8_t *restrict clear, real thr_hi,
        uint8_t *restrict hi) {
    if (hi) DK(box_points_lanes)(A, N, rg, bc, bR, bh, thr, COLLIDE_NARROW, clear, thr_hi, hi, 1);
    else DK(box_points_lanes)(A, N, rg, bc, bR, bh, thr, COLLIDE_NARROW, clear, 0, NULL, 1);
}

/* Box w of the world row of each lane n0 .. n0 + m - 1 of c, gathered per lane (centre lc[3][], rotation
 * lR[9][], half extents lh[3][], rows COLLIDE_BLOCK apart) for DK(box_lanes). */
static inline void DK(gather_box)(const dk_collide *c, int64_t n0, int m, int64_t w, real *lc, real *lR, real *lh) {
    const real *bc = (const real *)c->bc, *bR = (const real *)c->bR, *bh = (const real *)c->bh;
    for (int l = 0; l < m; l++) {
        const int64_t o = WORLD_OF(c, n0, l) * c->Wb + w;
        for (int k = 0; k < 3; k++) lc[k * COLLIDE_BLOCK + l] = bc[3 * o + k], lh[k * COLLIDE_BLOCK + l] = bh[3 * o + k];
        for (int k = 0; k < 9; k++) lR[k * COLLIDE_BLOCK + l] = bR[9 * o + k];
    }
}

/* Cylinder w of the world row of each lane n0 .. n0 + m - 1 of c, gathered per lane (flat faces' centres
 * pa[3][], pb[3][], radius pr[], rows COLLIDE_BLOCK apart) for DK(cylinder_lanes). */
static inline void DK(gather_cylinder)(const dk_collide *c, int64_t n0, int m, int64_t w, real *pa, real *pb,
                                       real *pr) {
    const real *ya = (const real *)c->ya, *yb = (const real *)c->yb, *yr = (const real *)c->yr;
    for (int l = 0; l < m; l++) {
        const int64_t o = WORLD_OF(c, n0, l) * c->Wy + w;
        for (int k = 0; k < 3; k++)
            pa[k * COLLIDE_BLOCK + l] = ya[3 * o + k], pb[k * COLLIDE_BLOCK + l] = yb[3 * o + k];
        pr[l] = yr[o];
    }
}

/* Whether every lane's capsule (segment a_l - b_l, radius rg) keeps d >= T = rg + thr from the lanes' boxes
 * (given per lane: centre bc[3][], rotation bR[9][], half extents bh[3][]). Spheres (point): the exact signed
 * distance, any thr (DK(box_points)). Segments: thr >= 0 (the caller's contract), so a penetrating segment
 * fails. Apart, the distance of a segment and a box is the least of its ends' distances and its
 * distances to the box's 12 edges (a closest pair with the segment's interior and a face's interior has the
 * segment parallel to that face: sliding along it reaches an end or an edge at the same distance). */
static void DK(box_lanes)(const real *A, const real *B, int64_t N, real rg, const real *bc, const real *bR,
                          const real *bh, real thr, int point, int m, uint8_t *restrict clear, real thr_hi,
                          uint8_t *restrict hi) {
    if (point) {
        if (hi) DK(box_points_cover)(A, N, rg, bc, bR, bh, thr, m, clear, thr_hi, hi);
        else DK(box_points)(A, N, rg, bc, bR, bh, thr, m, clear);
        return;
    }
    for (int l = 0; l < m; l++) {
        const real dx = A[l] - bc[l], dy = A[N + l] - bc[COLLIDE_BLOCK + l], dz = A[2 * N + l] - bc[2 * COLLIDE_BLOCK + l];
        real p[3], d[3], h[3] = {bh[l], bh[COLLIDE_BLOCK + l], bh[2 * COLLIDE_BLOCK + l]};
        DK(box_frame)(bR + l, dx, dy, dz, p, p + 1, p + 2);
        const real T = rg + thr, Th = rg + (hi ? thr_hi : thr);
        real ex;
        real best = DK(box_point_d2)(p[0], p[1], p[2], h[0], h[1], h[2], &ex);
        const real ux = B[l] - A[l], uy = B[N + l] - A[N + l], uz = B[2 * N + l] - A[2 * N + l];
        DK(box_frame)(bR + l, ux, uy, uz, d, d + 1, d + 2);
        real e2 = DK(box_point_d2)(p[0] + d[0], p[1] + d[1], p[2] + d[2], h[0], h[1], h[2], &ex);
        best = e2 < best ? e2 : best;
        /* a cheap pass first: the segment's bounding sphere against the box's */
        const real len = (real)0.5 * (real)sqrt((double)(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]));
        const real mx = p[0] + (real)0.5 * d[0], my = p[1] + (real)0.5 * d[1], mz = p[2] + (real)0.5 * d[2];
        const real hr = (real)sqrt((double)(h[0] * h[0] + h[1] * h[1] + h[2] * h[2]));
        const real far = (real)sqrt((double)(mx * mx + my * my + mz * mz)) - len - hr;
        if (far >= Th) continue;
        if (best < T * T || DK(box_segment_meets)(p, d, h)) {
            clear[l] = 0;
            continue;
        }
        for (int k = 0; k < 3 && best >= T * T; k++) { /* the 4 edges along axis k */
            const int i = (k + 1) % 3, j = (k + 2) % 3;
            for (int sgn = 0; sgn < 4; sgn++) {
                real q[3], v[3] = {0, 0, 0}, s, t;
                q[k] = -h[k];
                q[i] = sgn & 1 ? h[i] : -h[i];
                q[j] = sgn & 2 ? h[j] : -h[j];
                v[k] = 2 * h[k];
                const real d2 = DK(segment_closest)(d[0], d[1], d[2], v[0], v[1], v[2], p[0] - q[0], p[1] - q[1],
                                                    p[2] - q[2], &s, &t);
                best = d2 < best ? d2 : best;
            }
        }
        clear[l] &= best >= T * T;
        if (hi) hi[l] &= best >= Th * Th;
    }
}

/* Lanes l .. l + 3 (those below m) of DK(cylinder_lanes_impl). */
static inline __attribute__((always_inline)) void DK(cylinder_v4)(const real *A, int64_t N, real rg, const real *ya,
        const real *yb, const real *yr, real thr, int l, int m, uint8_t *restrict clear, real thr_hi,
        uint8_t *restrict hi, const int full) {
#define LANES(p) DK(v4_load)((p), l, m, full)
    const DK(v4) zero = DK(v4_splat)(0), half = DK(v4_splat)((real)0.5);
    const DK(v4) ax = LANES(ya), ay = LANES(ya + COLLIDE_BLOCK), az = LANES(ya + 2 * COLLIDE_BLOCK);
    const DK(v4) ex = half * (LANES(yb) - ax), ey = half * (LANES(yb + COLLIDE_BLOCK) - ay),
                 ez = half * (LANES(yb + 2 * COLLIDE_BLOCK) - az);
    const DK(v4) hl = DK(v4_sqrt)(ex * ex + ey * ey + ez * ez);
    const DK(m4) deg = ~(hl > DK(v4_splat)((real)1e-12));
    const DK(v4) inv = DK(v4_splat)(1) / DK(v4_select)(deg, DK(v4_splat)(1), hl);
    const DK(v4) ux = DK(v4_select)(deg, zero, ex * inv), uy = DK(v4_select)(deg, zero, ey * inv),
                 uz = DK(v4_select)(deg, DK(v4_splat)(1), ez * inv);
    const DK(v4) wx = LANES(A) - ax - ex, wy = LANES(A + N) - ay - ey, wz = LANES(A + 2 * N) - az - ez;
    const DK(v4) z = wx * ux + wy * uy + wz * uz;
    DK(v4) rad2 = wx * wx + wy * wy + wz * wz - z * z;
    rad2 = DK(v4_max)(rad2, zero);
    const DK(v4) qx = DK(v4_sqrt)(rad2) - LANES(yr), qz = DK(v4_abs)(z) - hl;
#undef LANES
    const DK(v4) ox = DK(v4_max)(qx, zero), oz = DK(v4_max)(qz, zero);
    const DK(v4) d = DK(v4_sqrt)(ox * ox + oz * oz) + DK(v4_min)(DK(v4_max)(qx, qz), zero) - DK(v4_splat)(rg);
    DK(v4_and_into)(clear, l, m, d >= DK(v4_splat)(thr), full);
    if (hi) DK(v4_and_into)(hi, l, m, d >= DK(v4_splat)(thr_hi), full);
}

/* Whether every lane's sphere (centre a_l, radius rg) keeps d >= T_l = rg + thr from the lanes' cylinders
 * (flat faces' centres ya, yb [3][], radius yr []): the closed-form field of diffkin.collision.cylinders
 * (axial coordinate z, radial distance rho, half-length hl: q = (rho - r, |z| - hl), d = |max(q, 0)| +
 * min(max(q), 0)), four lanes at a time. */
static inline __attribute__((always_inline)) void DK(cylinder_lanes_impl)(const real *A, int64_t N, real rg,
        const real *ya, const real *yb, const real *yr, real thr, int m, uint8_t *restrict clear, real thr_hi,
        uint8_t *restrict hi) {
    int l = 0;
    for (; l + 4 <= m; l += 4) DK(cylinder_v4)(A, N, rg, ya, yb, yr, thr, l, m, clear, thr_hi, hi, 1);
    if (l < m) DK(cylinder_v4)(A, N, rg, ya, yb, yr, thr, l, m, clear, thr_hi, hi, 0);
}

static void DK(cylinder_lanes)(const real *A, int64_t N, real rg,
        const real *ya, const real *yb, const real *yr, real thr, int m, uint8_t *restrict clear) {
    DK(cylinder_lanes_impl)(A, N, rg, ya, yb, yr, thr, m, clear, 0, NULL);
}

/* DK(cylinder_lanes) deciding each lane at thr_hi as well, into hi (&=) */
static void DK(cylinder_lanes_cover)(const real *A, int64_t N,
        real rg, const real *ya, const real *yb, const real *yr, real thr, int m, uint8_t *restrict clear,
        real thr_hi, uint8_t *restrict hi) {
    DK(cylinder_lanes_impl)(A, N, rg, ya, yb, yr, thr, m, clear, thr_hi, hi);
}

/* Whether some lane of the block is still clear (a block whose lanes all collide stops early). */
static inline int DK(any_clear)(const uint8_t *clear, int m) {
    uint8_t any = 0;
    for (int l = 0; l < m; l++) any |= clear[l];
    return any;
}

/* Whether the boxes [lo1, hi1] and [lo2, hi2] (3 each) are at least T apart (T <= 0: apart at all): then every
 * entry of the block between what they bound is clear and is skipped. */
static inline int DK(aabb_apart)(const real *lo1, const real *hi1, const real *lo2, const real *hi2, real T) {
    real g2 = 0;
    for (int k = 0; k < 3; k++) {
        real gap = lo2[k] - hi1[k], gap2 = lo1[k] - hi2[k];
        gap = gap > gap2 ? gap : gap2;
        g2 += gap > 0 ? gap * gap : 0;
    }
    return T > 0 ? g2 >= T * T : (T <= 0) & (g2 > 0); /* a NaN threshold: never apart */
}

/* DK(aabb_apart) of boxes l .. l + 3 (those below n; given axis-major: axis k's row from k * stride) and the box
 * [olo, ohi], box i at least T[i] apart (T[i] <= 0: apart at all, NaN: never), the same arithmetic: the
 * apart lanes set */
static inline __attribute__((always_inline)) DK(m4) DK(apart_v4)(const real *lo, const real *hi, int64_t stride,
        int l, int n, const int full, const real *olo, const real *ohi, DK(v4) T) {
    const DK(v4) zero = DK(v4_splat)(0);
    DK(v4) g2 = zero;
    for (int k = 0; k < 3; k++) {
        const DK(v4) a = DK(v4_splat)(olo[k]) - DK(v4_load)(hi + k * stride, l, n, full);
        const DK(v4) b = DK(v4_load)(lo + k * stride, l, n, full) - DK(v4_splat)(ohi[k]);
        const DK(v4) gap = DK(v4_max)(a, b);
        g2 += DK(v4_select)(gap > zero, gap * gap, zero);
    }
    return ((T > zero) & (g2 >= T * T)) | ((T <= zero) & (g2 > zero));
}

/* near[u] = !DK(aabb_apart)(box u, [olo, ohi], T) for the n boxes [lo, hi] given axis-major (axis k's row from
 * k * stride), four boxes at a time (DK(apart_v4)): a group's test against an object, about a third of a
 * narrow decision's time as a branch each. */
static inline void DK(boxes_near)(const real *lo, const real *hi, int64_t stride, int64_t n, const real *olo,
                                  const real *ohi, real T, uint8_t *restrict near) {
    for (int l = 0; l < n; l += 4) {
        const int full = l + 4 <= n;
        const DK(m4) apart = full ? DK(apart_v4)(lo, hi, stride, l, (int)n, 1, olo, ohi, DK(v4_splat)(T))
                                  : DK(apart_v4)(lo, hi, stride, l, (int)n, 0, olo, ohi, DK(v4_splat)(T));
        for (int i = 0; i < 4 && l + i < n; i++) near[l + i] = !(apart[i] & 1);
    }
}

/* Bit i set where geom g0 + i (i < n <= 64; boxes axis-major, rows CULL_GEOMS apart) is not at least
 * r[g0 + i] + T from the box [olo, ohi]: DK(aabb_apart) four geoms at a time (DK(apart_v4)), a group's geoms
 * against an object (a branch each took about a sixth of a narrow decision's time). */
static inline uint64_t DK(geoms_near)(const real *lo, const real *hi, const real *r, int64_t g0, int n,
                                      const real *olo, const real *ohi, real T) {
    uint64_t bits = 0;
    for (int l = 0; l < n; l += 4) {
        const int full = l + 4 <= n;
        const DK(m4) apart =
            full ? DK(apart_v4)(lo + g0, hi + g0, CULL_GEOMS, l, n, 1, olo, ohi, DK(v4_load)(r + g0, l, n, 1) + T)
                 : DK(apart_v4)(lo + g0, hi + g0, CULL_GEOMS, l, n, 0, olo, ohi, DK(v4_load)(r + g0, l, n, 0) + T);
        for (int i = 0; i < 4 && l + i < n; i++) bits |= (uint64_t)!(apart[i] & 1) << (l + i);
    }
    return bits;
}

/* Lanes 0 .. m-1 below the first one that collides (m itself when none does). */
static inline int DK(first_hit)(const uint8_t *clear, int m) {
    for (int l = 0; l < m; l++)
        if (!clear[l]) return l;
    return m;
}

/* Whether every lane of the block is still clear. */
static inline int DK(all_clear)(const uint8_t *clear, int m) {
    uint8_t all = 1;
    for (int l = 0; l < m; l++) all &= clear[l];
    return all;
}

/* Whether some lane is still to be decided: one is clear; with COLLIDE_FIRST, one before the first colliding
 * lane, and *m shrinks to that lane (the lanes past it are dropped from every later test); with COLLIDE_ANY,
 * no lane collides yet. */
static inline int DK(lanes_left)(const uint8_t *clear, int *m, const int mode) {
    if (mode == COLLIDE_FIRST) return (*m = DK(first_hit)(clear, *m)) > 0;
    if (mode == COLLIDE_ANY || mode == COLLIDE_COVER) return DK(all_clear)(clear, *m);
    return DK(any_clear)(clear, *m);
}

/* The decisions of the block's lanes n0 .. n0 + m - 1 into ok (&=). With COLLIDE_FIRST (an edge's first
 * colliding sample wanted: dk_plan_edges), lanes past the first colliding one found so far are dropped from
 * every later test: ok is then exact up to and including the first colliding lane and says nothing about the
 * lanes after it. With COLLIDE_ANY (an edge taken whole or not at all: the search, the shortcuts), the block
 * stops at the first collision found in any lane: every lane of ok is then clear when all are, and else
 * some colliding lane is 0 (a lane of ok at 0 always collides; one at 1 may too). */
static inline __attribute__((always_inline)) void DK(collide_lanes)(const dk_collide *c, const CollideRuns *R,
                                                                    int64_t n0, int m, uint8_t *restrict ok,
                                                                    const int mode, CollideHint *hint,
                                                                    const real thr_hi, uint8_t *restrict hi_ok) {
    const int64_t N = c->N, G = c->G;
    const int m0 = m;
    const real *A = (const real *)c->A, *B = (const real *)c->B, *r = (const real *)c->r;
    const real thr = (real)(c->margin + c->slack);
    const int any = mode == COLLIDE_ANY || mode == COLLIDE_COVER; /* the block stops at a collision */
    /* with COLLIDE_COVER every lane decided at thr_hi as well (hi): the culls at the larger threshold, so
     * that an entry culled is apart at both */
    const real cthr = mode == COLLIDE_COVER ? thr_hi : thr;
    uint8_t hic[COLLIDE_BLOCK];
    uint8_t *hi = mode == COLLIDE_COVER ? hic : NULL;
    for (int l = 0; hi && l < m; l++) hic[l] = 1;
    real d2[COLLIDE_BLOCK];
    uint8_t clear[COLLIDE_BLOCK];
    int64_t wl[COLLIDE_BLOCK];
    for (int l = 0; l < m; l++) clear[l] = 1, wl[l] = WORLD_OF(c, n0, l);
    /* The broad phase of the block: each geom's axis-aligned box over the block's lanes (the samples of an
     * edge lie close together), against each object's box when the lanes share one world, and against each
     * other for the self pairs. */
    const int64_t NG = R->NG; /* 0: no culling */
    real olo[3], ohi[3];
    int same = m > 0; /* every lane in one world row: its objects read in place, not gathered per lane */
    for (int l = 1; l < m && same; l++) same = wl[l] == wl[0];
    const int cull = NG > 0 && same;
    const int64_t w0 = m > 0 ? wl[0] : 0;
    /* The level above (CollideRuns), formed in the same pass: each group bounded by the union of its geoms'
     * boxes, each grown by its radius. A group box at least thr from an object's box puts each geom's box at
     * least r_g + thr from it (the gap vector g of two boxes and g' of the grown ones: |g| >= |g'| + r), so
     * the group's geoms are skipped as one; the self pairs alike with both groups grown (r_i + r_j). */
    real gslo[3 * CULL_GEOMS], gshi[3 * CULL_GEOMS]; /* axis-major: axis k of group u at k CULL_GEOMS + u */
    uint8_t gnear[CULL_GEOMS];
    /* each geom's box, axis-major: axis k of geom g at k CULL_GEOMS + g (DK(geoms_near)) */
    real gxlo[3 * CULL_GEOMS], gxhi[3 * CULL_GEOMS];
    real ulo[3] = {(real)INFINITY, (real)INFINITY, (real)INFINITY};
    real uhi[3] = {-(real)INFINITY, -(real)INFINITY, -(real)INFINITY};
    int unan = 0; /* a NaN geom (its box NaN below) or radius turns its group's box into NaN: never apart */
    uint8_t rnan[3 * CULL_GEOMS];
    if (NG && m > 0) /* each geom's box over the lanes: row 3 g + k of A (and B) is its axis k */
        DK(rows_range)(A + n0, A == B ? NULL : B + n0, N, 3 * G, m, gxlo, gxhi, rnan);
    for (int64_t g = 0, u = 0; g < G && NG && m > 0; g++) {
        const int nan = rnan[3 * g] | rnan[3 * g + 1] | rnan[3 * g + 2]; /* a NaN coordinate in some lane */
        if (nan) /* NaN on every axis: each gap 0, never apart (nor its group) */
            for (int k = 0; k < 3; k++) gxlo[k * CULL_GEOMS + g] = gxhi[k * CULL_GEOMS + g] = (real)NAN;
        const real rg = r[g] > 0 ? r[g] : 0;
        unan |= r[g] != r[g];
        for (int k = 0; k < 3; k++) {
            const real a = gxlo[k * CULL_GEOMS + g] - rg, b = gxhi[k * CULL_GEOMS + g] + rg;
            unan |= (a != a) | (b != b);
            ulo[k] = a < ulo[k] ? a : ulo[k];
            uhi[k] = b > uhi[k] ? b : uhi[k];
        }
        if (g + 1 == R->start[u + 1]) { /* the group's last geom */
            for (int k = 0; k < 3; k++) { /* NaN: aabb_apart's gaps 0 on every axis, never apart */
                gslo[k * CULL_GEOMS + u] = unan ? (real)NAN : ulo[k], gshi[k * CULL_GEOMS + u] = unan ? (real)NAN : uhi[k];
                ulo[k] = (real)INFINITY, uhi[k] = -(real)INFINITY;
            }
            unan = 0;
            u++;
        }
    }
    /* the geoms g0 .. g1 - 1 of each group in turn (one group of all without culling), the groups whose box
     * is at least thr from the object's box (olo, ohi) skipped (DK(boxes_near)), and in the others each geom
     * whose box is at least r_g + thr from it (DK(geoms_near): the group's near geoms as bits, 64 at a time,
     * taken in order) */
    const int64_t NU = NG ? NG : 1;
#define GROUP_GEOMS(g) \
    if (cull) DK(boxes_near)(gslo, gshi, CULL_GEOMS, NG, olo, ohi, cthr, gnear); \
    for (int64_t u_ = 0; u_ < NU; u_++) \
        if (!cull || gnear[u_]) \
            for (int64_t b_ = NG ? R->start[u_] : 0, e_ = NG ? R->start[u_ + 1] : G; b_ < e_; b_ += 64) \
                for (uint64_t n_ = e_ - b_ < 64 ? (uint64_t)(e_ - b_) : 64, \
                              bits_ = cull ? DK(geoms_near)(gxlo, gxhi, r, b_, (int)n_, olo, ohi, cthr) \
                                           : (n_ == 64 ? ~0ull : (1ull << n_) - 1); \
                     bits_; bits_ &= bits_ - 1) \
                    for (int64_t g = b_ + __builtin_ctzll(bits_), once_ = 1; once_; once_ = 0)
    const real *wa = (const real *)c->wa, *wb = (const real *)c->wb, *wr = (const real *)c->wr;
    const real *hs = (const real *)c->hs;
    real pa[4 * COLLIDE_BLOCK], pb[3 * COLLIDE_BLOCK], pr[COLLIDE_BLOCK]; /* pa: 4 rows for a half-space */
    for (int64_t w = 0; w < c->Wr; w++) { /* round objects: a segment per lane (its world's), gathered once */
        if (!DK(lanes_left)(clear, &m, mode)) goto done;
        for (int l = 0; l < m; l++) {
            const int64_t o = wl[l] * c->Wr + w;
            for (int k = 0; k < 3; k++) {
                pa[k * COLLIDE_BLOCK + l] = wa[3 * o + k];
                pb[k * COLLIDE_BLOCK + l] = wb[3 * o + k];
            }
            pr[l] = wr[o];
        }
        for (int k = 0; k < 3 && cull; k++) {
            const real x = pa[k * COLLIDE_BLOCK], y = pb[k * COLLIDE_BLOCK];
            olo[k] = (x < y ? x : y) - pr[0], ohi[k] = (x < y ? y : x) + pr[0];
        }
        GROUP_GEOMS(g) {
            if (c->skip_r && c->skip_r[g * c->Wr + w]) continue;
            DK(segments_d2)(A + g * 3 * N + n0, B + g * 3 * N + n0, N, pa, pb, COLLIDE_BLOCK, m, d2);
            for (int l = 0; l < m; l++) {
                const real T = r[g] + pr[l] + thr;
                clear[l] &= (T <= 0) | (d2[l] >= T * T);
            }
            for (int l = 0; hi && l < m; l++) {
                const real T = r[g] + pr[l] + thr_hi;
                hi[l] &= (T <= 0) | (d2[l] >= T * T);
            }
            if (any && !DK(all_clear)(clear, m)) goto done;
        }
    }
    for (int64_t h = 0; h < c->H; h++) { /* {x : n.x <= offset}: min(n.a, n.b) - offset - r */
        if (!DK(lanes_left)(clear, &m, mode)) goto done;
        for (int l = 0; l < m; l++)
            for (int k = 0; k < 4; k++) pa[k * COLLIDE_BLOCK + l] = hs[4 * (wl[l] * c->H + h) + k];
        for (int64_t g = 0; g < G; g++) {
            if (c->skip_h && c->skip_h[g * c->H + h]) continue;
            const real *Ag = A + g * 3 * N + n0, *Bg = B + g * 3 * N + n0;
            for (int l = 0; l < m; l++) {
                const real nx = pa[l], ny = pa[COLLIDE_BLOCK + l], nz = pa[2 * COLLIDE_BLOCK + l];
                const real off = pa[3 * COLLIDE_BLOCK + l];
                real da = nx * Ag[l] + ny * Ag[N + l] + nz * Ag[2 * N + l];
                real db = nx * Bg[l] + ny * Bg[N + l] + nz * Bg[2 * N + l];
                real d = (da < db ? da : db) - off - r[g];
                clear[l] &= d - (real)c->margin >= (real)c->slack;
                if (hi) hi[l] &= d >= thr_hi;
            }
        }
    }
    if (c->Wb) { /* boxes (segments: thr >= 0, the caller's contract) */
        const real *bc = (const real *)c->bc, *bR = (const real *)c->bR, *bh = (const real *)c->bh;
        real lc[3 * COLLIDE_BLOCK], lR[9 * COLLIDE_BLOCK], lh[3 * COLLIDE_BLOCK];
        for (int64_t w = 0; w < c->Wb; w++) {
            if (!DK(lanes_left)(clear, &m, mode)) goto done;
            int gathered = 0; /* the box per lane, gathered once a geom is near it (most objects are not) */
            for (int k = 0; k < 3 && cull; k++) { /* the box's extent along world axis k: sum_j |R_kj| h_j */
                const real *Rw = bR + 9 * (w0 * c->Wb + w), *h = bh + 3 * (w0 * c->Wb + w);
                const real e = (Rw[3 * k] < 0 ? -Rw[3 * k] : Rw[3 * k]) * h[0] +
                               (Rw[3 * k + 1] < 0 ? -Rw[3 * k + 1] : Rw[3 * k + 1]) * h[1] +
                               (Rw[3 * k + 2] < 0 ? -Rw[3 * k + 2] : Rw[3 * k + 2]) * h[2];
                olo[k] = bc[3 * (w0 * c->Wb + w) + k] - e, ohi[k] = bc[3 * (w0 * c->Wb + w) + k] + e;
            }
            GROUP_GEOMS(g) {
                if (c->skip_b && c->skip_b[g * c->Wb + w]) continue;
                const int point = c->point ? c->point[g] : 0;
                if (point && same) { /* a sphere, one box for the block, read in place (m a constant where
                                      * DK(collide_any_narrow) and DK(collide_cover_narrow) inline this) */
                    const int64_t ob = w0 * c->Wb + w;
                    const real *Ag = A + g * 3 * N + n0;
                    if (m == COLLIDE_NARROW)
                        DK(box_points_one_narrow)(Ag, N, r[g], bc + 3 * ob, bR + 9 * ob, bh + 3 * ob, thr, clear,
                                                  thr_hi, hi);
                    else
                        DK(box_points_one)(Ag, N, r[g], bc + 3 * ob, bR + 9 * ob, bh + 3 * ob, thr, m, clear, thr_hi,
                                           hi);
                } else { /* lanes in several rows, or a capsule: the box gathered per lane */
                    if (!gathered) {
                        DK(gather_box)(c, n0, m, w, lc, lR, lh);
                        gathered = 1;
                    }
                    DK(box_lanes)(A + g * 3 * N + n0, B + g * 3 * N + n0, N, r[g], lc, lR, lh, thr, point, m, clear,
                                  thr_hi, hi);
                }
                if (any && !DK(all_clear)(clear, m)) {
                    if (hint && point) hint->w = w, hint->g = g, hint->cyl = 0;
                    goto done;
                }
            }
        }
    }
    if (c->Wy && c->point) { /* cylinders: the sphere geoms only (the caller decides the others) */
        const real *ya = (const real *)c->ya, *yb = (const real *)c->yb, *yr = (const real *)c->yr;
        for (int64_t w = 0; w < c->Wy; w++) {
            if (!DK(lanes_left)(clear, &m, mode)) goto done;
            int gathered = 0; /* the cylinder per lane, gathered once a geom is near it */
            for (int k = 0; k < 3 && cull; k++) { /* the faces' centres and the radius every way */
                const int64_t o = w0 * c->Wy + w;
                const real x = ya[3 * o + k], y = yb[3 * o + k];
                olo[k] = (x < y ? x : y) - yr[o], ohi[k] = (x < y ? y : x) + yr[o];
            }
            GROUP_GEOMS(g) {
                if (!c->point[g] || (c->skip_y && c->skip_y[g * c->Wy + w])) continue;
                if (!gathered) {
                    DK(gather_cylinder)(c, n0, m, w, pa, pb, pr);
                    gathered = 1;
                }
                if (hi) DK(cylinder_lanes_cover)(A + g * 3 * N + n0, N, r[g], pa, pb, pr, thr, m, clear, thr_hi, hi);
                else DK(cylinder_lanes)(A + g * 3 * N + n0, N, r[g], pa, pb, pr, thr, m, clear);
                if (any && !DK(all_clear)(clear, m)) {
                    if (hint) hint->w = w, hint->g = g, hint->cyl = 1;
                    goto done;
                }
            }
        }
    }
#undef GROUP_GEOMS
    if (!DK(lanes_left)(clear, &m, mode)) goto done;
    /* the self pairs (last: the world rejects most colliding samples), a run of pairs of one pair of groups
     * (CollideRuns) skipped at once where the groups' boxes are apart */
    const int64_t *pi = NG ? R->pi : c->pi, *pj = NG ? R->pj : c->pj;
    int64_t tested = 0;
    for (int64_t p = 0; p < c->P;) {
        const int64_t end = NG ? R->end[p] : c->P;
        int64_t v = 0, u0 = 0;
        real vlo[3] = {0, 0, 0}, vhi[3] = {0, 0, 0}; /* group v's box (with NG) */
        uint64_t ibits = 0; /* with near_i, bit i - u0: geom i near group v (DK(geoms_near), u's geoms at once) */
        int near_i = 0;
        if (NG) {
            const int64_t u = R->of[pi[p]];
            v = R->of[pj[p]];
            real ulo3[3], uhi3[3];
            DK(box_at)(gslo, gshi, u, ulo3, uhi3);
            DK(box_at)(gslo, gshi, v, vlo, vhi);
            if (DK(aabb_apart)(ulo3, uhi3, vlo, vhi, cthr)) {
                p = end;
                continue;
            }
            u0 = R->start[u];
            near_i = R->start[u + 1] - u0 <= 64;
            if (near_i) ibits = DK(geoms_near)(gxlo, gxhi, r, u0, (int)(R->start[u + 1] - u0), vlo, vhi, cthr);
        }
        int64_t at_i = -1; /* a run's pairs of one geom i: consecutive in the callers' order (else tested again) */
        real ilo[3] = {0, 0, 0}, ihi[3] = {0, 0, 0}; /* geom i's box (with NG) */
        for (; p < end; p++) {
            const int64_t i = pi[p], j = pj[p];
            if (NG && i != at_i) { /* i's box r_i + thr from group v's (grown by each r_j): all of i's pairs there */
                at_i = i;
                DK(box_at)(gxlo, gxhi, i, ilo, ihi);
                if (near_i ? !((ibits >> (i - u0)) & 1) : DK(aabb_apart)(ilo, ihi, vlo, vhi, r[i] + cthr)) {
                    while (p + 1 < end && pi[p + 1] == i) p++;
                    continue;
                }
            }
            const real T = r[i] + r[j] + thr, Tc = r[i] + r[j] + cthr, Th = r[i] + r[j] + thr_hi;
            if (Tc <= 0) continue;
            if (NG) {
                real jlo[3], jhi[3];
                DK(box_at)(gxlo, gxhi, j, jlo, jhi);
                if (DK(aabb_apart)(ilo, ihi, jlo, jhi, Tc)) continue;
            }
            const real *Ai = A + i * 3 * N + n0, *Aj = A + j * 3 * N + n0;
            if (c->point && c->point[i] && c->point[j]) { /* two spheres: their centres */
                for (int l = 0; l < m; l++) {
                    const real dx = Ai[l] - Aj[l], dy = Ai[N + l] - Aj[N + l], dz = Ai[2 * N + l] - Aj[2 * N + l];
                    d2[l] = dx * dx + dy * dy + dz * dz;
                }
            } else {
                DK(segments_d2)(Ai, B + i * 3 * N + n0, N, Aj, B + j * 3 * N + n0, N, m, d2);
            }
            for (int l = 0; l < m; l++) clear[l] &= (T <= 0) | (d2[l] >= T * T); /* T <= 0 < Tc: cover only */
            for (int l = 0; hi && l < m; l++) hi[l] &= d2[l] >= Th * Th;
            if ((any || (++tested & 15) == 0) && !DK(lanes_left)(clear, &m, mode)) goto done;
        }
    }
done:
    for (int l = 0; l < m0; l++) ok[n0 + l] &= clear[l];
    for (int l = 0; hi && l < m0; l++) hi_ok[n0 + l] = clear[l] & hic[l];
}

static void DK(collide_block)(const dk_collide *c, const CollideRuns *R, int64_t n0, int m, uint8_t *restrict ok) {
    DK(collide_lanes)(c, R, n0, m, ok, COLLIDE_ALL, NULL, 0, NULL);
}

/* DK(collide_block) for a caller that reads ok only up to its first colliding lane (DK(collide_lanes)). */
static void DK(collide_first)(const dk_collide *c, const CollideRuns *R, int64_t n0, int m,
                              uint8_t *restrict ok) {
    DK(collide_lanes)(c, R, n0, m, ok, COLLIDE_FIRST, NULL, 0, NULL);
}

/* DK(collide_block) for a caller that reads only whether some lane collides (DK(collide_lanes)). */
static void DK(collide_any)(const dk_collide *c, const CollideRuns *R, int64_t n0, int m, uint8_t *restrict ok) {
    DK(collide_lanes)(c, R, n0, m, ok, COLLIDE_ANY, NULL, 0, NULL);
}

/* DK(collide_any), each lane decided at thr_hi as well: hi[l] = 1 where lane l is clear at both thresholds
 * (read only when ok has no 0: a block that stops early leaves it incomplete). */
static void DK(collide_cover)(const dk_collide *c, const CollideRuns *R, int64_t n0, int m, uint8_t *restrict ok,
                              real thr_hi, uint8_t *restrict hi) {
    DK(collide_lanes)(c, R, n0, m, ok, COLLIDE_COVER, NULL, thr_hi, hi);
}

/* DK(collide_any) of lanes 0 .. COLLIDE_NARROW - 1, a constant: every loop over the lanes has a constant
 * trip count (an edge's first block, about half the planner's decision time); a collision of a sphere and a
 * box or a cylinder found is kept in hint. */
static void DK(collide_any_narrow)(const dk_collide *c, const CollideRuns *R, uint8_t *restrict ok,
                                   CollideHint *hint) {
    DK(collide_lanes)(c, R, 0, COLLIDE_NARROW, ok, COLLIDE_ANY, hint, 0, NULL);
}

/* DK(collide_any_narrow) as DK(collide_cover). */
static void DK(collide_cover_narrow)(const dk_collide *c, const CollideRuns *R, uint8_t *restrict ok,
                                     CollideHint *hint, real thr_hi, uint8_t *restrict hi) {
    DK(collide_lanes)(c, R, 0, COLLIDE_NARROW, ok, COLLIDE_COVER, hint, thr_hi, hi);
}

/* Whether hint's sphere geom meets hint's box or cylinder in some lane of lanes 0 .. COLLIDE_NARROW - 1 (each
 * in its world row), the same test as DK(collide_lanes)'s: its lanes' decisions into ok (&=). Only the geom's
 * own rows of c->A are read. */
static int DK(collide_hint)(const dk_collide *c, const CollideHint *hint, uint8_t *restrict ok) {
    const int64_t g = hint->g, N = c->N;
    const real *A = (const real *)c->A + g * 3 * N, rg = ((const real *)c->r)[g], thr = (real)(c->margin + c->slack);
    uint8_t clear[COLLIDE_NARROW];
    memset(clear, 1, COLLIDE_NARROW);
    int one_row = 1; /* the planner's blocks: a box read in place */
    for (int l = 1; l < COLLIDE_NARROW; l++) one_row &= WORLD_OF(c, 0, l) == WORLD_OF(c, 0, 0);
    if (hint->cyl) {
        real pa[3 * COLLIDE_BLOCK], pb[3 * COLLIDE_BLOCK], pr[COLLIDE_BLOCK];
        DK(gather_cylinder)(c, 0, COLLIDE_NARROW, hint->w, pa, pb, pr);
        DK(cylinder_lanes)(A, N, rg, pa, pb, pr, thr, COLLIDE_NARROW, clear);
    } else if (one_row) {
        const int64_t o = WORLD_OF(c, 0, 0) * c->Wb + hint->w;
        DK(box_points_one_narrow)(A, N, rg, (const real *)c->bc + 3 * o, (const real *)c->bR + 9 * o,
                                  (const real *)c->bh + 3 * o, thr, clear, 0, NULL);
    } else {
        real lc[3 * COLLIDE_BLOCK], lR[9 * COLLIDE_BLOCK], lh[3 * COLLIDE_BLOCK];
        DK(gather_box)(c, 0, COLLIDE_NARROW, hint->w, lc, lR, lh);
        DK(box_points_narrow)(A, N, rg, lc, lR, lh, thr, clear);
    }
    for (int l = 0; l < COLLIDE_NARROW; l++) ok[l] &= clear[l];
    return !DK(all_clear)(clear, COLLIDE_NARROW);
}

/* The decisions of c's N configurations: blocks shared between threads, the groups runs of CULL_GROUP
 * geoms (without memory for the ordered pairs, no culling: the same decisions but for rounding at the
 * threshold, where a cull's exact box gap and the narrow phase's rounded squared distance may disagree). */
static void DK(dk_collide)(const dk_collide *c) {
    CollideRuns R;
    collide_runs_init(&R, c->G, c->P, c->pi, c->pj, NULL);
    const int64_t nblocks = (c->N + COLLIDE_BLOCK - 1) / COLLIDE_BLOCK;
    int nthreads = (int)(c->nthreads > 1 && nblocks > 1 ? c->nthreads : 1);
#pragma omp parallel for schedule(dynamic, 4) num_threads(nthreads) if (nthreads > 1)
    for (int64_t k = 0; k < nblocks; k++) {
        const int64_t n0 = k * COLLIDE_BLOCK;
        const int m = (int)(c->N - n0 < COLLIDE_BLOCK ? c->N - n0 : COLLIDE_BLOCK);
        DK(collide_block)(c, &R, n0, m, c->ok);
    }
    collide_runs_free(&R);
}
