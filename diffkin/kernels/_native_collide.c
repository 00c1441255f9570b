/* The collision decisions of the IK's checks in one call (included by _native.c once per real type, like
 * _native_solve.c): whether every checked capsule pair and every capsule against every round world object
 * (spheres, capsules, points: segments with a radius) and half-space has d - margin >= slack, per
 * configuration. diffkin/collision/robot.py (RobotCollision._clear) places the capsules and calls it; boxes
 * stay with the torch broad phase.
 *
 * Capsules are given component-major as the placement product leaves them: A and B (G x 3 x N) the segment
 * ends, r (G) the radii. The distance of two segments is Ericson's closest points of two segments
 * (Real-Time Collision Detection, 5.1.9) written without branches, so the loop over the configurations of a
 * block vectorises; degenerate segments (points) take the clamped formulas. The test compares squared
 * centre distances with (r_a + r_b + margin + slack)^2: no square root. Configurations run in blocks of
 * COLLIDE_BLOCK (the block's capsules stay in cache while every pair is tested), blocks shared between
 * threads.
 */
#ifndef DK_COLLIDE_ONCE
#define DK_COLLIDE_ONCE
#define COLLIDE_BLOCK 256
#endif

/* Ericson's closest points of the segments p + s u and q + t v (s, t in [0, 1]; w = p - q) without
 * branches: every division runs on a safe denominator and a select picks the case. Writes s and t and
 * returns the squared distance. Inlined where it is used: the lane loop of DK(segments_d2) vectorises,
 * the differential-IK step's collision rows (_native_velocity.c) take the closest points of one pair. */
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

static void DK(collide_block)(const dk_collide *c, int64_t n0, int m, uint8_t *restrict ok) {
    const int64_t N = c->N, G = c->G;
    const real *A = (const real *)c->A, *B = (const real *)c->B, *r = (const real *)c->r;
    const real thr = (real)(c->margin + c->slack);
    real d2[COLLIDE_BLOCK];
    uint8_t clear[COLLIDE_BLOCK];
    for (int l = 0; l < m; l++) clear[l] = 1;
    for (int64_t p = 0; p < c->P; p++) { /* the self pairs */
        const int64_t i = c->pi[p], j = c->pj[p];
        const real T = r[i] + r[j] + thr;
        if (T <= 0) continue;
        DK(segments_d2)(A + i * 3 * N + n0, B + i * 3 * N + n0, N, A + j * 3 * N + n0, B + j * 3 * N + n0, N,
                        m, d2);
        for (int l = 0; l < m; l++) clear[l] &= d2[l] >= T * T;
    }
    const real *wa = (const real *)c->wa, *wb = (const real *)c->wb, *wr = (const real *)c->wr;
    const real *hs = (const real *)c->hs;
    real pa[3 * COLLIDE_BLOCK], pb[3 * COLLIDE_BLOCK];
    for (int64_t w = 0; w < c->Wr; w++) { /* round objects: a segment, copied to the m lanes once */
        for (int k = 0; k < 3; k++)
            for (int l = 0; l < m; l++) {
                pa[k * COLLIDE_BLOCK + l] = wa[3 * w + k];
                pb[k * COLLIDE_BLOCK + l] = wb[3 * w + k];
            }
        for (int64_t g = 0; g < G; g++) {
            if (c->skip_r && c->skip_r[g * c->Wr + w]) continue;
            const real T = r[g] + wr[w] + thr;
            if (T <= 0) continue;
            DK(segments_d2)(A + g * 3 * N + n0, B + g * 3 * N + n0, N, pa, pb, COLLIDE_BLOCK, m, d2);
            for (int l = 0; l < m; l++) clear[l] &= d2[l] >= T * T;
        }
    }
    for (int64_t g = 0; g < G && c->H; g++) {
        const real *Ag = A + g * 3 * N + n0, *Bg = B + g * 3 * N + n0;
        for (int64_t h = 0; h < c->H; h++) { /* {x : n.x <= offset}: min(n.a, n.b) - offset - r */
            if (c->skip_h && c->skip_h[g * c->H + h]) continue;
            const real nx = hs[4 * h], ny = hs[4 * h + 1], nz = hs[4 * h + 2], off = hs[4 * h + 3];
            for (int l = 0; l < m; l++) {
                real da = nx * Ag[l] + ny * Ag[N + l] + nz * Ag[2 * N + l];
                real db = nx * Bg[l] + ny * Bg[N + l] + nz * Bg[2 * N + l];
                real d = (da < db ? da : db) - off - r[g];
                clear[l] &= d - (real)c->margin >= (real)c->slack;
            }
        }
    }
    for (int l = 0; l < m; l++) ok[n0 + l] &= clear[l];
}

static void DK(dk_collide)(const dk_collide *c) {
    const int64_t nblocks = (c->N + COLLIDE_BLOCK - 1) / COLLIDE_BLOCK;
    int nthreads = (int)(c->nthreads > 1 && nblocks > 1 ? c->nthreads : 1);
#pragma omp parallel for schedule(dynamic, 4) num_threads(nthreads) if (nthreads > 1)
    for (int64_t k = 0; k < nblocks; k++) {
        const int64_t n0 = k * COLLIDE_BLOCK;
        const int m = (int)(c->N - n0 < COLLIDE_BLOCK ? c->N - n0 : COLLIDE_BLOCK);
        DK(collide_block)(c, n0, m, c->ok);
    }
}
