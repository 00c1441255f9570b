/* The whole of diffkin.ik.solve in one C call (included by _native.c once per real type, like its second
 * half): seeding, the Levenberg-Marquardt iteration (3.59), harvest, stall detection, re-seeding
 * and the final check, for every chain the fused pass takes: 1-DOF joints, and ball and free joints whose
 * unit quaternions are stepped on the manifold (DK(integrate)). diffkin/ik/_native_solve.py prepares the
 * arrays.
 *
 * The algorithm is diffkin/ik/_lm.py's, step for step (its torch backend serves CUDA and the CPU without
 * the library; on the same inputs both give the same flags and q to rounding): every target runs its seeds
 * one after another. Per LM step of a row: evaluate e at u; converged (max |e_p| <= tp margin and max theta
 * <= to margin): the target is done with this u; else every `iters` steps of the seed (age % iters == 0) a
 * seed older than min_seed_iterations whose merit did not shrink by stall_ratio since the last check, or
 * one at max_iterations, is finished (the best finished seed of each target is kept) and the target's next
 * seed starts; else u <- u (+) delta (3.59). Work is split into chunks of CHUNK targets, each solved by one
 * thread on the W lanes of DK(block): a lane holds one target's current seed, and a free lane takes the
 * chunk's next target. A target's result depends only on its own inputs, so the solve is the same for
 * every thread count and schedule.
 *
 * Seed s of target t: s < S the user's seed (t, s); s < S + R the library configuration with the (s - S)-th
 * nearest pose (squared distance of positions plus feature_weight times that of the rotation columns); else
 * column (t n_seeds + s) mod P of the pool of uniform draws (nu = Ns + 3 Nb per column: one per scalar
 * coordinate in q order, then three per quaternion, as ConfigurationSpace.from_uniform), mapped to u
 * uniform in q (u = asin((2r - 1) (1 - 1e-6)) on bounded joints, lo + 2 h r on the other scalars, as
 * JointMap.sample_u; a quaternion by Shoemake's map, eta >= 0).
 *
 * The configuration space (Space below): q has n = nq coordinates, a step nv velocities; a scalar
 * coordinate (R, P motions) moves by its velocity (additive on u), a quaternion (S motion: 4 coordinates,
 * 3 velocities, the angular velocity in the rotated frame) by Q <- normalise(Q) (x) exp(w / 2), as
 * ConfigurationSpace.integrate (mj_integratePos, dt = 1). Both maps are read off the frames' motion,
 * qidx and vidx, so the packed chain is the one description.
 *
 * The result q = c + h sin(u) (bounded), wrapped by 2 pi towards the centre on revolute variables, clamped
 * into [qlo, qhi] when clamp (scalars; quaternions are normalised); its exact errors come from one more FK;
 * success = errors within the tolerances (not the margin) and, when clamp, the scalars within [qlo, qhi].
 */
#ifndef DK_SOLVE_ONCE_TYPES
#define DK_SOLVE_ONCE_TYPES
#define CHUNK 128 /* targets per chunk: a fixed number, so the answers do not depend on the thread count */
#define MAX_RANKS 64 /* library ranks a target may ask for (lib_ranks; more: DK_RANGE_ERROR) */
#define MAX_ENDS 64 /* end links the nearest-pose search takes (more: no library seeds) */

/* The arguments of dk_solve and dk_solve_one (X(type, name, what)): the chain (a pointer to its dk_args,
 * checked as dk_fk checks it), the LM constants, the targets, the seeds and the outputs. A new solver option
 * is a field here (and a bump of DK_SOLVE_VERSION with native.SolveArgs); dk_args, the FK's, keeps its
 * layout. Reals are of the chain's real_bytes. */
#define DK_SOLVE_FIELDS(X) \
    X(int64_t, version, "DK_SOLVE_VERSION") \
    X(int64_t, size, "sizeof(dk_solve_args)") \
    X(int64_t, nthreads, "threads to use (at least 1)") \
    X(const dk_args *, chain, "the chain's arrays (their call fields unused)") \
    X(int64_t, iters, "steps between two stall checks") \
    X(int64_t, n_targets, "N") \
    X(const void *, pd, "[3K*N] reals") \
    X(const void *, xd, "[3K*N] reals, NULL: position only") \
    X(const void *, yd, "[3K*N] reals") \
    X(const void *, zd, "[3K*N] reals") \
    X(const void *, sqrt_w, "[rows] reals") \
    X(const void *, jc, "[n] reals") \
    X(const void *, jh, "[n] reals") \
    X(const uint8_t *, bounded, "[n]") \
    X(double, damping2, "the constant damping of (3.59)") \
    X(double, error_damping, "the weight of the error-dependent damping") \
    X(double, tol_p, "position tolerance") \
    X(double, tol_o, "orientation tolerance") \
    X(double, margin, "converged within the tolerances times this") \
    X(int64_t, n_seeds, "most seeds per target") \
    X(int64_t, max_iterations, "most LM iterations per seed (iters: steps between stall checks)") \
    X(int64_t, min_seed_iterations, "a seed younger than this is never stalled") \
    X(double, stall_ratio, "stalled when the merit did not shrink by this factor over a check") \
    X(int64_t, n_user, "S user seeds per target") \
    X(const void *, user_u, "[N*S*n] reals") \
    X(int64_t, n_lib, "L library configurations") \
    X(int64_t, lib_ranks, "R nearest library poses tried per target") \
    X(const void *, lib_u, "[L*n] reals") \
    X(const void *, lib_pose, "[12K*L] reals, feature-major: p, x, y, z of every end link")  \
    X(double, feature_weight, "weight of the rotation columns in the nearest-pose distance") \
    X(int64_t, n_pool, "P random draws") \
    X(const void *, pool, "[P*n] uniform reals in [0, 1)") \
    X(const void *, qlo, "[n] reals, the limits of the final check") \
    X(const void *, qhi, "[n] reals") \
    X(const uint8_t *, wrap, "[n] revolute variables, wrapped by 2 pi towards the centre") \
    X(int64_t, clamp, "clamp into [qlo, qhi] and require it for success") \
    X(void *, q_out, "[N*n] reals out") \
    X(int64_t *, iters_out, "[N] out") \
    X(int64_t *, seeds_out, "[N] out") \
    X(void *, pos_err, "[N] reals out") \
    X(void *, ori_err, "[N] reals out") \
    X(uint8_t *, success, "[N] out") \
    X(int64_t, target_stride, "entries between a target column's rows (0: N; 4: one row-major pose)")
typedef struct dk_solve_args { DK_SOLVE_FIELDS(DK_DECLARE) } dk_solve_args;
DK_LAYOUT(solve, dk_solve_args, DK_SOLVE_FIELDS, DK_SOLVE_VERSION)

/* A 4 KiB-aligned work space of at least `bytes`, kept by the calling thread between calls and grown when a
 * call needs more (one single-threaded solve's work space per calling thread, never released). */
static __thread void *kept_ptr;
static __thread size_t kept_bytes;
static void *kept_space(size_t bytes) {
    if (bytes > kept_bytes) {
        free(kept_ptr);
        kept_bytes = (bytes + 4095) / 4096 * 4096;
        kept_ptr = aligned_alloc(4096, kept_bytes);
        if (!kept_ptr) kept_bytes = 0;
    }
    return kept_ptr;
}

/* The work space of a call that runs no other kernel while it holds it (the banded solve, the clip rows):
 * the calling thread's kept space up to DK_KEEP_MAX bytes (faulted in once: a 2.5 MB banded work space
 * freshly allocated cost 0.3 ms of page faults a call of 1.2 ms), a fresh block beyond it (*owned = 1: the
 * caller frees it). NULL when memory ran out. */
#define DK_KEEP_MAX ((size_t)64 << 20)
static void *work_space(size_t bytes, int *owned) {
    *owned = bytes > DK_KEEP_MAX;
    return *owned ? aligned_alloc(4096, (bytes + 4095) / 4096 * 4096) : kept_space(bytes);
}

/* The pool of a one-target call drawn here instead of by torch (dk_solve_one with a seed): the stream of
 * torch.rand(n, generator=torch.Generator().manual_seed(seed)) on the CPU, which is MT19937 (ATen's
 * at::mt19937: the reference initialisation of the low 32 bits of the seed, the reference twist and
 * tempering) read as 53-bit doubles from two words (the first the high half, ATen's random64) or 24-bit
 * floats from one; tests/test_native_solve_one.py compares the streams with torch's. Drawn lazily: a
 * target that a library seed solves draws nothing (torch would fill the whole pool: ~4 us of one call). */
#define MT_N 624
#define MT_M 397
typedef struct {
    uint32_t mt[MT_N];
    int next;          /* the next word of mt to temper; MT_N: twist first */
    int seeded;
    uint64_t seed;
    int64_t drawn;     /* uniforms drawn into buf */
    void *buf;         /* the pool's reals (the caller's work space) */
} dk_stream;

static void stream_seed(dk_stream *g) {
    g->mt[0] = (uint32_t)(g->seed & 0xffffffffu);
    for (uint32_t j = 1; j < MT_N; j++) g->mt[j] = 1812433253u * (g->mt[j - 1] ^ (g->mt[j - 1] >> 30)) + j;
    g->next = MT_N;
    g->seeded = 1;
}

static uint32_t stream_word(dk_stream *g) {
    if (g->next >= MT_N) {
        for (int j = 0; j < MT_N; j++) {
            const uint32_t y = (g->mt[j] & 0x80000000u) | (g->mt[(j + 1) % MT_N] & 0x7fffffffu);
            g->mt[j] = g->mt[(j + MT_M) % MT_N] ^ (y >> 1) ^ ((y & 1u) ? 0x9908b0dfu : 0u);
        }
        g->next = 0;
    }
    uint32_t y = g->mt[g->next++];
    y ^= y >> 11;
    y ^= (y << 7) & 0x9d2c5680u;
    y ^= (y << 15) & 0xefc60000u;
    return y ^ (y >> 18);
}

typedef struct { /* the configuration space of the chain (see the top of this file) */
    int n, nv, nb, nu;       /* coordinates, velocities, quaternions, uniforms per random seed */
    int32_t *vq;             /* [nv] the coordinate a scalar velocity moves, -1 in a quaternion */
    int32_t *qs, *vs;        /* [nb] each quaternion's first coordinate and first velocity */
    int32_t *slot;           /* [n] a scalar's index among the scalars (its uniform), -1 in a quaternion */
} Space;

/* The space of the chain s from its frames (an S frame: one quaternion; an R or P frame: scalar qidx moved
 * by velocity vidx; mimic frames repeat their leader's pair); returns -1 when memory ran out. */
static int space_read(const Shape *s, Space *sp) {
    const int n = s->n, nv = s->nv;
    int32_t *all = (int32_t *)malloc(sizeof(int32_t) * (size_t)(nv + 2 * n + n + 1));
    if (!all) return -1;
    sp->n = n, sp->nv = nv, sp->nb = 0;
    sp->vq = all, sp->qs = all + nv, sp->vs = sp->qs + n, sp->slot = sp->vs + n;
    for (int v = 0; v < nv; v++) sp->vq[v] = -1;
    for (int i = 0; i < n; i++) sp->slot[i] = 0;
    for (int j = 0; j < s->J; j++) {
        if (s->motion[j] != DK_MOTION_S) {
            sp->vq[s->vidx[j]] = s->qidx[j];
            continue;
        }
        int seen = 0;
        for (int b = 0; b < sp->nb; b++) seen |= sp->qs[b] == s->qidx[j];
        if (seen) continue;
        sp->qs[sp->nb] = s->qidx[j];
        sp->vs[sp->nb++] = s->vidx[j];
        for (int c = 0; c < 4; c++) sp->slot[s->qidx[j] + c] = -1;
    }
    int k = 0;
    for (int i = 0; i < n; i++)
        if (sp->slot[i] >= 0) sp->slot[i] = k++;
    sp->nu = k + 3 * sp->nb;
    return 0;
}

/* acc + x y and acc - x y with one rounding where the CPU has FMA: GCC fuses them in the vector loops over
 * lanes but keeps a scalar chain (a sum in a register) as a multiply and an add (its FMA-chain tuning), and
 * a lane's numbers must not depend on how many lanes step together. */
#ifdef __FMA__
#define DK_MULADD(acc, x, y) (sizeof(real) == 8 ? (real)fma((double)(x), (double)(y), (double)(acc)) \
                                                : (real)fmaf((float)(x), (float)(y), (float)(acc)))
#else
#define DK_MULADD(acc, x, y) ((acc) + (x) * (y))
#endif
#define DK_MULSUB(acc, x, y) DK_MULADD(acc, -(x), y)

typedef struct { /* the structural non-zeros of the end links' Jacobians */
    int32_t *cols;  /* [K*nv] end link k's columns, ascending (count[k] of them): its ancestors' velocities */
    int32_t *count; /* [K] */
    uint8_t *moves; /* [K*nv] column v moves end link k (the columns in cols) */
} Support;

/* The support of every end link of s (the columns DK(block) writes; the others of its Jacobian stay 0):
 * one block in sup->cols, freed with it; returns -1 when memory ran out. */
static int support_read(const Shape *s, Support *sup) {
    const int K = s->K, nv = s->nv;
    int32_t *all = (int32_t *)malloc(sizeof(int32_t) * (size_t)(K * nv + K) + (size_t)(K * nv) + 1);
    if (!all) return -1;
    sup->cols = all, sup->count = all + K * nv, sup->moves = (uint8_t *)(sup->count + K);
    memset(sup->moves, 0, (size_t)(K * nv));
    for (int k = 0; k < K; k++)
        for (int j = 0; j < s->J; j++)
            if (s->anc[k * s->J + j]) /* an S frame: three velocities */
                for (int c = 0; c < (s->motion[j] == DK_MOTION_S ? 3 : 1); c++)
                    sup->moves[k * nv + s->vidx[j] + c] = 1;
    for (int k = 0; k < K; k++) {
        sup->count[k] = 0;
        for (int v = 0; v < nv; v++)
            if (sup->moves[k * nv + v]) sup->cols[k * nv + sup->count[k]++] = v;
    }
    return 0;
}
#endif

/* q and dq/du of the first nw of the W lanes of u (n x W, lane-major): q = c + h sin(u) on bounded joints,
 * else q = u. */
static void DK(map_u)(int n, const uint8_t *bounded, const real *jc, const real *jh, const real *ul,
                      real *ql, real *dl, const int nw) {
    for (int i = 0; i < n; i++) {
        double uu[W], sn[W], cs[W];
        const real *ui = ul + (size_t)i * W;
        real *qi = ql + (size_t)i * W, *di = dl + (size_t)i * W;
        if (!bounded[i]) {
            for (int l = 0; l < nw; l++) { qi[l] = ui[l]; di[l] = 1; }
            continue;
        }
        for (int l = 0; l < nw; l++) uu[l] = (double)ui[l];
        sincos_lanes(uu, sn, cs, nw);
        for (int l = 0; l < nw; l++) {
            qi[l] = jc[i] + jh[i] * (real)sn[l];
            di[l] = jh[i] * (real)cs[l];
        }
    }
}

/* Normalise the quaternion of lane l at qi (4 rows of W lanes) in place; one of norm ~0 becomes the
 * identity (as diffkin._numerics.stable_normalize and the FK's S motion: the threshold DK_QSMALL; scaled by
 * the largest |entry| before the squares, so entries of 1e160 do not overflow). */
static void DK(unit_quaternion)(real *qi, int l) {
    double x[4], mx = 0, nn = 0;
    for (int c = 0; c < 4; c++) {
        x[c] = (double)qi[(size_t)c * W + l];
        mx = fabs(x[c]) > mx ? fabs(x[c]) : mx;
    }
    const double back = mx > (double)DK_QSMALL ? mx : 1; /* below the threshold: unscaled (1/mx stays finite) */
    for (int c = 0; c < 4; c++) {
        x[c] /= back;
        nn += x[c] * x[c];
    }
    const double ns = sqrt(nn);
    const int small = !(back * ns > (double)DK_QSMALL);
    for (int c = 0; c < 4; c++) qi[(size_t)c * W + l] = (real)(small ? (c == 0) : x[c] / ns);
}

/* The configuration update u <- u (+) delta of lane l (u lane-major, n x W; delta nv, `stride` apart):
 * scalars u += their velocity, quaternions Q <- normalise(Q) (x) exp(w / 2), exp(w / 2) = (cos(th / 2),
 * sin(th / 2) w / th), th = |w| (ConfigurationSpace.integrate; not made eta >= 0, so that the step is
 * continuous in w). */
static void DK(integrate)(const Space *sp, real *ul, int l, const real *delta, int stride) {
    for (int v = 0; v < sp->nv; v++)
        if (sp->vq[v] >= 0) ul[(size_t)sp->vq[v] * W + l] += delta[(size_t)v * stride];
    for (int b = 0; b < sp->nb; b++) {
        real *qi = ul + (size_t)sp->qs[b] * W;
        DK(unit_quaternion)(qi, l);
        const real *w = delta + (size_t)sp->vs[b] * stride;
        const double wx = w[0], wy = w[stride], wz = w[2 * stride];
        const double h = 0.5 * sqrt(wx * wx + wy * wy + wz * wz);
        const double e0 = cos(h), s = h < 1e-4 ? 0.5 * (1 - h * h / 6) : 0.5 * sin(h) / h; /* sinc(h) / 2 */
        const double ev[3] = {s * wx, s * wy, s * wz};
        const double q0 = qi[l], q1 = qi[W + l], q2 = qi[2 * W + l], q3 = qi[3 * W + l];
        qi[l] = (real)(q0 * e0 - q1 * ev[0] - q2 * ev[1] - q3 * ev[2]);
        qi[W + l] = (real)(q0 * ev[0] + e0 * q1 + q2 * ev[2] - q3 * ev[1]);
        qi[2 * W + l] = (real)(q0 * ev[1] + e0 * q2 + q3 * ev[0] - q1 * ev[2]);
        qi[3 * W + l] = (real)(q0 * ev[2] + e0 * q3 + q1 * ev[1] - q2 * ev[0]);
    }
}

typedef struct { /* the fixed inputs of a solve, read once */
    const dk_solve_args *a; /* the solve's arguments (the chain's are read into s and pp) */
    Shape s;
    DK(Params) pp;
    Space sp;
    Support sup;
    int K, n, nv, r, d, pos_only;
    int64_t N, ts, S, L, R, P, nseeds, maxit, minit, every;
    real tp, to, margin, damping2, mu, stall, w2;
    const real *pd, *xd, *yd, *zd, *sqrt_w, *jc, *jh, *user_u, *lib_u, *lib_pose, *pool, *qlo, *qhi;
    const uint8_t *bounded, *wrap;
    real *best_merit; /* [N] */
    dk_stream *stream; /* not NULL: the pool is drawn from it as the seeds need it (one target, one thread) */
} DK(Solve);

/* The stream's uniforms up to index `upto` (exclusive) into its buffer, in stream order. */
static void DK(draw_upto)(dk_stream *g, int64_t upto) {
    real *buf = (real *)g->buf;
    if (g->drawn < upto && !g->seeded) stream_seed(g);
    for (; g->drawn < upto; g->drawn++) {
        if (sizeof(real) == 8) {
            const uint64_t hi = stream_word(g), lo = stream_word(g);
            buf[g->drawn] = (real)((double)(((hi << 32) | lo) & ((1ull << 53) - 1)) * 0x1p-53);
        } else {
            buf[g->drawn] = (real)((double)(stream_word(g) & ((1u << 24) - 1)) * 0x1p-24);
        }
    }
}

/* The error e (r rows: [p_d - p_e; theta r] per end link, or p_d - p_e) of lane l against target t, its
 * worst position error *pn (a scaled norm: no overflow) and angle *ang (DK(rotvec)). */
static void DK(lane_error)(const DK(Solve) *S, const real *ends, int l, int64_t t, real *e, real *pn,
                           real *ang) {
    const int64_t N = S->ts; /* the stride of the targets' columns */
    const real *cols[3] = {S->xd, S->yd, S->zd};
    *pn = 0;
    *ang = 0;
    for (int k = 0; k < S->K; k++) {
        const real *E = ends + (size_t)k * 12 * W;
        real *ek = e + (S->pos_only ? 3 : 6) * k, big = 0, sq = 0;
        for (int c = 0; c < 3; c++) {
            ek[c] = S->pd[(int64_t)(3 * k + c) * N + t] - E[(4 * c + 3) * W + l];
            big = fabs((double)ek[c]) > big ? (real)fabs((double)ek[c]) : big;
        }
        for (int c = 0; c < 3 && big > 0; c++) sq += (ek[c] / big) * (ek[c] / big); /* no overflow */
        const real nk = big * (real)sqrt((double)sq);
        *pn = nk > *pn ? nk : *pn;
        if (S->pos_only) continue;
        const real *rc[3] = {cols[0] + (int64_t)3 * k * N + t, cols[1] + (int64_t)3 * k * N + t,
                             cols[2] + (int64_t)3 * k * N + t};
        const real th = DK(rotvec)(E, l, rc, N, ek + 3);
        *ang = th > *ang ? th : *ang;
    }
}

/* Per thread: dq/du (n x W), then for the m lanes that step this iteration, lane-major (column j of each
 * array is the j-th stepping lane, lanes[j]): e (r x W), J_w (r x nv x W), A (d x d x W), y (d x W), delta
 * (nv x W), lambda (W); e1 (r) one lane's error. */
typedef struct { real *dqdu, *Jw, *e, *A, *y, *delta, *lam, *e1; int32_t *lanes; } DK(LMWork);

/* Solve A x = b in place on LN lanes (A d x d x W: its lower triangle, overwritten by the Cholesky factor;
 * b d x W), a Cholesky factorisation on each lane (pivots clamped to a tiny positive value, as
 * kernels/dls.py). Every entry's sum runs in registers over k in order (four rows of the factor at once:
 * independent chains), so a lane's numbers are those of the plain loops whatever LN (16, 8 or 1 where this
 * is inlined). */
static inline __attribute__((always_inline)) void DK(spd_solve_block)(real *restrict A, real *restrict b,
                                                                      int d, const int LN) {
    const real tiny = (real)sqrt((double)DK_TINY);
#define DK_ROW(i, c) (A + ((size_t)(i) * d + (c)) * W)
    for (int j = 0; j < d; j++) {
        real *restrict Ajj = DK_ROW(j, j), s[W];
        for (int l = 0; l < LN; l++) s[l] = Ajj[l];
        for (int k = 0; k < j; k++) {
            const real *restrict Ajk = DK_ROW(j, k);
            for (int l = 0; l < LN; l++) s[l] = DK_MULSUB(s[l], Ajk[l], Ajk[l]);
        }
        for (int l = 0; l < LN; l++) Ajj[l] = (real)sqrt((double)(s[l] > tiny ? s[l] : tiny));
        int i = j + 1;
        for (; i + 4 <= d; i += 4) {
            real s0[W], s1[W], s2[W], s3[W];
            for (int l = 0; l < LN; l++) {
                s0[l] = DK_ROW(i, j)[l], s1[l] = DK_ROW(i + 1, j)[l];
                s2[l] = DK_ROW(i + 2, j)[l], s3[l] = DK_ROW(i + 3, j)[l];
            }
            for (int k = 0; k < j; k++) {
                const real *restrict Ajk = DK_ROW(j, k), *restrict R0 = DK_ROW(i, k);
                const real *restrict R1 = DK_ROW(i + 1, k);
                const real *restrict R2 = DK_ROW(i + 2, k), *restrict R3 = DK_ROW(i + 3, k);
                for (int l = 0; l < LN; l++) {
                    s0[l] = DK_MULSUB(s0[l], R0[l], Ajk[l]);
                    s1[l] = DK_MULSUB(s1[l], R1[l], Ajk[l]);
                    s2[l] = DK_MULSUB(s2[l], R2[l], Ajk[l]);
                    s3[l] = DK_MULSUB(s3[l], R3[l], Ajk[l]);
                }
            }
            for (int l = 0; l < LN; l++) {
                DK_ROW(i, j)[l] = s0[l] / Ajj[l], DK_ROW(i + 1, j)[l] = s1[l] / Ajj[l];
                DK_ROW(i + 2, j)[l] = s2[l] / Ajj[l], DK_ROW(i + 3, j)[l] = s3[l] / Ajj[l];
            }
        }
        for (; i < d; i++) {
            real *restrict Aij = DK_ROW(i, j);
            for (int l = 0; l < LN; l++) s[l] = Aij[l];
            for (int k = 0; k < j; k++) {
                const real *restrict Aik = DK_ROW(i, k), *restrict Ajk = DK_ROW(j, k);
                for (int l = 0; l < LN; l++) s[l] = DK_MULSUB(s[l], Aik[l], Ajk[l]);
            }
            for (int l = 0; l < LN; l++) Aij[l] = s[l] / Ajj[l];
        }
    }
    for (int i = 0; i < d; i++) { /* L y = b */
        real *restrict bi = b + (size_t)i * W, s[W];
        for (int l = 0; l < LN; l++) s[l] = bi[l];
        for (int k = 0; k < i; k++)
            for (int l = 0; l < LN; l++) s[l] = DK_MULSUB(s[l], DK_ROW(i, k)[l], b[(size_t)k * W + l]);
        for (int l = 0; l < LN; l++) bi[l] = s[l] / DK_ROW(i, i)[l];
    }
    for (int i = d - 1; i >= 0; i--) { /* L^T x = y */
        real *restrict bi = b + (size_t)i * W, s[W];
        for (int l = 0; l < LN; l++) s[l] = bi[l];
        for (int k = i + 1; k < d; k++)
            for (int l = 0; l < LN; l++) s[l] = DK_MULSUB(s[l], DK_ROW(k, i)[l], b[(size_t)k * W + l]);
        for (int l = 0; l < LN; l++) bi[l] = s[l] / DK_ROW(i, i)[l];
    }
#undef DK_ROW
}

/* DK(spd_solve_block) on the first m lanes: 16 or 8 at once (vector registers), the rest one by one. */
static void DK(spd_solve_lanes)(real *restrict A, real *restrict b, int d, int m) {
    int l0 = 0;
    if (m == W) {
        DK(spd_solve_block)(A, b, d, W);
        return;
    }
    for (; l0 + 8 <= m; l0 += 8) DK(spd_solve_block)(A + l0, b + l0, d, 8);
    for (; l0 < m; l0++) DK(spd_solve_block)(A + l0, b + l0, d, 1);
}

/* J_w = diag(sqrt_w) J diag(dq/du) of the m stepping lanes (J: nv columns; dq/du of a scalar velocity's
 * coordinate, 1 in a quaternion, as JointMap.dq_du), gathered from the block's Jacobians Jb on each end
 * link's support (the other entries of J_w are never read: DK(lanes_delta) sums over the supports), and
 * the weighted errors e_w with lambda = damping2 + mu |e_w|^2. */
static void DK(lanes_weigh)(const DK(Solve) *S, const real *Jb, int m, DK(LMWork) *w) {
    const int n = S->nv, r = S->r, rows = S->pos_only ? 3 : 6;
    const int32_t *vq = S->sp.vq, *lanes = w->lanes;
    real *restrict e = w->e, *restrict lam = w->lam;
    for (int l = 0; l < m; l++) lam[l] = 0;
    for (int a = 0; a < r; a++)
        for (int l = 0; l < m; l++) {
            e[(size_t)a * W + l] *= S->sqrt_w[a];
            lam[l] = DK_MULADD(lam[l], e[(size_t)a * W + l], e[(size_t)a * W + l]);
        }
    for (int l = 0; l < m; l++) lam[l] = S->damping2 + S->mu * lam[l];
    const int dense = lanes[m - 1] == m - 1; /* the stepping lanes are 0 .. m - 1 (lanes ascend): no gather */
    for (int k = 0; k < S->K; k++)
        for (int a = 0; a < rows; a++)
            for (int s = 0; s < S->sup.count[k]; s++) {
                const int row = rows * k + a, i = S->sup.cols[k * n + s];
                const real *restrict src = Jb + ((size_t)k * 6 * n + (size_t)a * n + i) * W;
                const real sw = S->sqrt_w[row];
                const real *restrict dq = vq[i] >= 0 ? w->dqdu + (size_t)vq[i] * W : NULL;
                real *restrict dst = w->Jw + ((size_t)row * n + i) * W;
                if (dense && dq)
                    for (int l = 0; l < m; l++) dst[l] = src[l] * sw * dq[l];
                else if (dense)
                    for (int l = 0; l < m; l++) dst[l] = src[l] * sw;
                else
                    for (int l = 0; l < m; l++) dst[l] = src[lanes[l]] * sw * (dq ? dq[lanes[l]] : 1);
            }
}

/* A += the `rows` rows of one end link (from row0 of J_w, n columns) in J_w^T J_w on its support (s
 * columns `cols`): A's lower triangle on those columns, the rows added in order (the sum over all rows of
 * J_w in their order, less the terms that are 0 by structure). rows is 3 or 6 where this is inlined. */
static inline __attribute__((always_inline)) void DK(gram_rows)(const real *restrict Jw, int row0, int n,
                                                                const int32_t *cols, int s, real *restrict A,
                                                                int d, int m, const int rows) {
    for (int sa = 0; sa < s; sa++)
        for (int sc = 0; sc <= sa; sc++) {
            const int a = cols[sa], c = cols[sc];
            real *restrict Aac = A + ((size_t)a * d + c) * W;
            const real *restrict x = Jw + ((size_t)row0 * n + a) * W;
            const real *restrict z = Jw + ((size_t)row0 * n + c) * W;
            for (int l = 0; l < m; l++) {
                real acc = Aac[l];
                for (int j = 0; j < rows; j++)
                    acc = DK_MULADD(acc, x[(size_t)j * n * W + l], z[(size_t)j * n * W + l]);
                Aac[l] = acc;
            }
        }
}

/* The damped least-squares steps (3.59) of the m stepping lanes into delta: delta = J_w^T (J_w J_w^T +
 * lambda I)^-1 e_w, or the n x n normal equations when r > n (J_w, e_w, lambda from DK(lanes_weigh)). The
 * lanes are innermost: a block of stepping lanes runs on vector registers (1.8x a lane at a time for the
 * Panda, 1.3x for the G1 floating base with four end links), a single target's one lane as before. Every
 * product sums over the end links' supports only: a row of end link k is 0 outside its ancestors' columns
 * (the G1 with 14 end links: J_w^T J_w takes a tenth of the dense products), and the terms that remain
 * are added in the dense sum's order, so the steps are the dense ones to the bit. */
static void DK(lanes_delta)(const DK(Solve) *S, const real *Jb, int m, DK(LMWork) *w) {
    const int n = S->nv, r = S->r, d = S->d, rows = S->pos_only ? 3 : 6; /* n: the step's nv columns */
    const Support *sup = &S->sup;
    DK(lanes_weigh)(S, Jb, m, w);
    const real *restrict Jw = w->Jw, *restrict e = w->e, *restrict lam = w->lam;
    real *restrict A = w->A, *restrict y = w->y, *restrict delta = w->delta;
    if (r > n) { /* J_w^T J_w: each end link's rows on its support, the links in row order */
        for (int a = 0; a < n; a++)
            for (int c = 0; c <= a; c++)
                for (int l = 0; l < m; l++) A[((size_t)a * d + c) * W + l] = 0;
        for (int k = 0; k < S->K; k++) {
            if (rows == 3) DK(gram_rows)(Jw, 3 * k, n, sup->cols + (size_t)k * n, sup->count[k], A, d, m, 3);
            else DK(gram_rows)(Jw, 6 * k, n, sup->cols + (size_t)k * n, sup->count[k], A, d, m, 6);
        }
    } else { /* J_w J_w^T: rows a, c over the columns both of their end links move */
        for (int a = 0; a < r; a++) {
            const int ka = a / rows;
            const int32_t *ca = sup->cols + (size_t)ka * n;
            const uint8_t *mv = sup->moves;
            for (int c = 0; c <= a; c++) {
                const uint8_t *mc = mv + (size_t)(c / rows) * n;
                real *restrict Aac = A + ((size_t)a * d + c) * W;
                if (m == 1) { /* one stepping lane (a single target): the sum in a register, the same order */
                    real acc = 0;
                    for (int s = 0; s < sup->count[ka]; s++)
                        if (mc[ca[s]])
                            acc = DK_MULADD(acc, Jw[((size_t)a * n + ca[s]) * W],
                                            Jw[((size_t)c * n + ca[s]) * W]);
                    Aac[0] = acc;
                    continue;
                }
                for (int l = 0; l < m; l++) Aac[l] = 0;
                for (int s = 0; s < sup->count[ka]; s++) {
                    if (!mc[ca[s]]) continue;
                    const real *restrict x = Jw + ((size_t)a * n + ca[s]) * W;
                    const real *restrict z = Jw + ((size_t)c * n + ca[s]) * W;
                    for (int l = 0; l < m; l++) Aac[l] = DK_MULADD(Aac[l], x[l], z[l]);
                }
            }
        }
    }
    const int rr = r <= n ? r : n;
    for (int a = 0; a < rr; a++)
        for (int l = 0; l < m; l++) A[((size_t)a * d + a) * W + l] += lam[l];
    if (r <= n) {
        for (int a = 0; a < r; a++)
            for (int l = 0; l < m; l++) y[(size_t)a * W + l] = e[(size_t)a * W + l];
        DK(spd_solve_lanes)(A, y, d, m);
    }
    for (int i = 0; i < n; i++) { /* J_w^T y, or the right-hand side J_w^T e_w: the rows that move column i */
        real *restrict di = delta + (size_t)i * W;
        const real *restrict v = r <= n ? y : e;
        if (m == 1) { /* one stepping lane: as above */
            real acc = 0;
            for (int k = 0; k < S->K; k++)
                for (int a = rows * k; a < rows * k + rows && sup->moves[(size_t)k * n + i]; a++)
                    acc = DK_MULADD(acc, Jw[((size_t)a * n + i) * W], v[(size_t)a * W]);
            di[0] = acc;
            continue;
        }
        for (int l = 0; l < m; l++) di[l] = 0;
        for (int k = 0; k < S->K; k++) {
            if (!sup->moves[(size_t)k * n + i]) continue;
            for (int a = rows * k; a < rows * k + rows; a++)
                for (int l = 0; l < m; l++)
                    di[l] = DK_MULADD(di[l], Jw[((size_t)a * n + i) * W + l], v[(size_t)a * W + l]);
        }
    }
    if (r > n) DK(spd_solve_lanes)(A, delta, d, m);
}

/* The R library indices of the poses nearest target t (nearest first) into nn. lib_pose is feature-major
 * (F x L), so the distances of NEAR_BLOCK library poses are one vectorised loop per feature (scalar over
 * features, this search was a quarter of a batched solve's time); the sums run over the features in the
 * same order either way. */
#ifndef NEAR_BLOCK
#define NEAR_BLOCK 64 /* <= 64: a block's candidates are the bits of one uint64_t */
#endif
static void DK(nearest)(const DK(Solve) *S, int64_t t, int32_t *nn) {
    const int K3 = 3 * S->K, F = S->pos_only ? K3 : 4 * K3;
    real best[MAX_RANKS], ft[12 * MAX_ENDS], wt[12 * MAX_ENDS];
    const real *tcol[4] = {S->pd, S->xd, S->yd, S->zd};
    const int64_t L = S->L;
    int R = (int)S->R;
    for (int c = 0; c < F; c++) { /* the target's features, once */
        ft[c] = tcol[c / K3][(int64_t)(c % K3) * S->ts + t];
        wt[c] = c < K3 ? 1 : S->w2;
    }
    for (int64_t j0 = 0; j0 < L; j0 += NEAR_BLOCK) {
        const int nb = (int)(L - j0 < NEAR_BLOCK ? L - j0 : NEAR_BLOCK);
        real d[NEAR_BLOCK];
        for (int jj = 0; jj < NEAR_BLOCK; jj++) d[jj] = 0;
        for (int c = 0; c < F; c++) {
            const real *f = S->lib_pose + (size_t)c * L + j0, tc = ft[c], w = wt[c];
            for (int jj = 0; jj < nb; jj++) d[jj] += w * (tc - f[jj]) * (tc - f[jj]);
        }
        /* the candidates: below the R-th best at the block's start (a bound: it only shrinks within) */
        const real worst = j0 >= R ? best[R - 1] : (real)INFINITY;
        uint64_t below = 0;
        for (int jj = 0; jj < nb; jj++) below |= (uint64_t)(d[jj] < worst) << jj;
        if (j0 < R) below = ~(uint64_t)0 >> (64 - nb); /* the first R fill the list whatever their value */
        for (; below; below &= below - 1) {
            const int jj = __builtin_ctzll(below);
            const int64_t j = j0 + jj;
            const real dist = d[jj];
            int at = (int)(j < R ? j : R); /* insertion into the sorted R best */
            if (at == R && !(dist < best[R - 1])) continue;
            if (at == R) at = R - 1;
            while (at > 0 && dist < best[at - 1]) {
                best[at] = best[at - 1];
                nn[at] = nn[at - 1];
                at--;
            }
            best[at] = dist;
            nn[at] = (int32_t)j;
        }
    }
}

/* Seed number s of target t (nn: its library ranks) into lane l of ul. */
static void DK(seed)(const DK(Solve) *S, int64_t t, int64_t s, const int32_t *nn, real *ul, int l) {
    const int n = S->n;
    if (s < S->S) {
        for (int i = 0; i < n; i++) ul[(size_t)i * W + l] = S->user_u[(t * S->S + s) * n + i];
        return;
    }
    if (s - S->S < S->R) {
        const real *lu = S->lib_u + (size_t)nn[s - S->S] * n;
        for (int i = 0; i < n; i++) ul[(size_t)i * W + l] = lu[i];
        return;
    }
    const Space *sp = &S->sp;
    const int64_t col = (t * S->nseeds + s) % S->P;
    if (S->stream) DK(draw_upto)(S->stream, (col + 1) * sp->nu);
    const real *r = (S->stream ? (const real *)S->stream->buf : S->pool) + (size_t)col * sp->nu;
    for (int i = 0; i < n; i++) {
        if (sp->slot[i] < 0) continue;
        const real ri = r[sp->slot[i]];
        const real v = S->bounded[i] ? (real)asin((double)((2 * ri - 1) * (real)(1.0 - 1e-6)))
                                     : (S->jc[i] - S->jh[i]) + 2 * S->jh[i] * ri;
        ul[(size_t)i * W + l] = v;
    }
    const double two_pi = 6.283185307179586;
    for (int b = 0; b < sp->nb; b++) { /* Shoemake: uniform on S^3, then eta >= 0 (from_uniform) */
        const real *rb = r + (sp->nu - 3 * sp->nb) + 3 * b;
        const double u1 = rb[0], a = two_pi * rb[1], c = two_pi * rb[2];
        const double r1 = sqrt(1 - u1 > 0 ? 1 - u1 : 0), r2 = sqrt(u1 > 0 ? u1 : 0);
        double Q[4] = {r1 * sin(a), r1 * cos(a), r2 * sin(c), r2 * cos(c)};
        const double sign = Q[0] < 0 ? -1 : 1;
        real *qi = ul + (size_t)sp->qs[b] * W;
        for (int k = 0; k < 4; k++) qi[(size_t)k * W + l] = (real)(sign * Q[k]);
        DK(unit_quaternion)(qi, l); /* as JointMap.u_of_q */
    }
}

typedef struct { /* the rows of one chunk: per lane (t < 0: free; prev: its last target) and per target */
    int64_t t0, t1, next, t[W], it[W], prev[W];
    real last[W];
    int32_t *nn;   /* [CHUNK * R] */
    uint8_t *done;       /* [CHUNK] */
} DK(Chunk);

/* Start a seed of target t in lane l (nothing when t has no seeds left); returns whether it did. */
static int DK(start)(const DK(Solve) *S, DK(Chunk) *c, int64_t t, real *ul, int l) {
    int64_t *seeds = S->a->seeds_out;
    const int64_t j = t - c->t0;
    if (t < 0 || c->done[j] || seeds[t] >= S->nseeds) return 0;
    if (seeds[t] == S->S && S->R) DK(nearest)(S, t, c->nn + j * S->R); /* before its first library seed */
    DK(seed)(S, t, seeds[t], c->nn + j * S->R, ul, l);
    if (seeds[t] == 0) /* a first best: every target ends with some u */
        for (int i = 0; i < S->n; i++) ((real *)S->a->q_out)[t * S->n + i] = ul[(size_t)i * W + l];
    seeds[t]++;
    c->t[l] = t;
    c->it[l] = 0;
    c->last[l] = (real)INFINITY;
    return 1;
}

/* Give a free lane l work: the next seed of its last target, else the first seed of the chunk's next
 * target. A target holds at most one lane and runs its seeds one after another, so its path depends on
 * nothing but its own inputs (the schedule of diffkin/ik/_lm.py, step for step). */
static void DK(refill)(const DK(Solve) *S, DK(Chunk) *c, real *ul, int l, int64_t last) {
    c->t[l] = -1;
    if (DK(start)(S, c, last, ul, l)) return;
    while (c->next < c->t1)
        if (DK(start)(S, c, c->next++, ul, l)) return;
}

/* Lane l's row ends: it converged (keep u, the target is done) or was finished with merit (keep u if
 * the target's best so far, the later of equal merits); the lane is refilled after the step. */
static void DK(finish)(const DK(Solve) *S, DK(Chunk) *c, real *ul, int l, int conv, real merit) {
    const int64_t t = c->t[l], j = t - c->t0;
    real *best = (real *)S->a->q_out + t * S->n;
    if (conv || merit <= S->best_merit[t]) {
        S->best_merit[t] = conv ? -1 : merit;
        for (int i = 0; i < S->n; i++) best[i] = ul[(size_t)i * W + l];
    }
    if (conv) c->done[j] = 1;
    c->t[l] = -1;
    c->prev[l] = t;
}

/* One LM step on the chunk's lanes, with harvest and stall checks. */
static void DK(chunk_step)(const DK(Solve) *S, DK(Chunk) *c, DK(Scratch) *sc, real *ul, DK(LMWork) *w) {
    int hi = 0; /* the lanes in use: lane 0 alone (a single target) takes the narrow block */
    for (int l = 0; l < W; l++) hi = c->t[l] >= 0 ? l + 1 : hi;
    const int nw = hi <= WN ? WN : W;
    DK(map_u)(S->n, S->bounded, S->jc, S->jh, ul, sc->qlanes, w->dqdu, nw);
    if (nw == W) DK(block)(&S->s, &S->pp, sc, 1);
    else DK(block_narrow)(&S->s, &S->pp, sc, 1);
    int64_t *iters = S->a->iters_out;
    int m = 0;
    for (int l = 0; l < W; l++) {
        const int64_t t = c->t[l];
        if (t < 0) continue;
        real pn, ang;
        DK(lane_error)(S, sc->ends, l, t, w->e1, &pn, &ang);
        iters[t]++;
        const int64_t age = ++c->it[l];
        if (pn <= S->tp * S->margin && ang <= S->to * S->margin) {
            DK(finish)(S, c, ul, l, 1, 0);
            continue;
        }
        const real merit = S->pos_only ? pn / S->tp : (pn / S->tp > ang / S->to ? pn / S->tp : ang / S->to);
        if (age % S->every == 0) {
            const int slow = age >= S->minit && !(merit <= S->stall * c->last[l]);
            c->last[l] = merit;
            if (slow || age >= S->maxit) {
                DK(finish)(S, c, ul, l, 0, merit);
                continue;
            }
        }
        for (int a = 0; a < S->r; a++) w->e[(size_t)a * W + m] = w->e1[a];
        w->lanes[m++] = l; /* steps below, with every lane that does */
    }
    if (m) DK(lanes_delta)(S, sc->Jb, m, w);
    for (int j = 0; j < m; j++) /* a lane retired meanwhile (its target converged) is refilled below */
        DK(integrate)(&S->sp, ul, w->lanes[j], w->delta + j, W);
    for (int l = 0; l < W; l++) /* after every row's checks: only targets still open take lanes */
        if (c->t[l] < 0) {
            DK(refill)(S, c, ul, l, c->prev[l]);
            c->prev[l] = -1;
        }
}

/* The final q of targets t0 .. t1 - 1 (their best u in q_out, replaced) and its exact check. */
static void DK(final_check)(const DK(Solve) *S, DK(Scratch) *sc, int64_t t0, int64_t t1, real *e) {
    const dk_solve_args *a = S->a;
    const int n = S->n;
    real *q = (real *)a->q_out, *pe = (real *)a->pos_err, *oe = (real *)a->ori_err;
    const double two_pi = 6.283185307179586;
    for (int64_t b0 = t0; b0 < t1; b0 += W) {
        const int nl = (int)(t1 - b0 < W ? t1 - b0 : W);
        for (int l = 0; l < W; l++) {
            real *qt = q + (b0 + (l < nl ? l : nl - 1)) * n;
            for (int i = 0; i < n && l < nl; i++) {
                if (S->sp.slot[i] < 0) continue; /* a quaternion: normalised below */
                double v = S->bounded[i] ? (double)S->jc[i] + (double)S->jh[i] * sin((double)qt[i]) : qt[i];
                if (S->wrap[i]) v -= two_pi * nearbyint((v - (double)S->jc[i]) / two_pi);
                if (a->clamp) v = v < S->qlo[i] ? S->qlo[i] : (v > S->qhi[i] ? S->qhi[i] : v);
                qt[i] = (real)v;
            }
            for (int i = 0; i < n; i++) sc->qlanes[(size_t)i * W + l] = qt[i];
            for (int b = 0; b < S->sp.nb && l < nl; b++) {
                real *qi = sc->qlanes + (size_t)S->sp.qs[b] * W;
                DK(unit_quaternion)(qi, l);
                for (int c = 0; c < 4; c++) qt[S->sp.qs[b] + c] = qi[(size_t)c * W + l];
            }
        }
        if (nl <= WN) DK(block_narrow)(&S->s, &S->pp, sc, 0);
        else DK(block)(&S->s, &S->pp, sc, 0);
        for (int l = 0; l < nl; l++) {
            const int64_t t = b0 + l;
            real pn, ang;
            DK(lane_error)(S, sc->ends, l, t, e, &pn, &ang);
            int ok = pn <= S->tp && (S->pos_only || ang <= S->to);
            for (int i = 0; i < n && a->clamp; i++)
                ok &= S->sp.slot[i] < 0 || (q[t * n + i] >= S->qlo[i] && q[t * n + i] <= S->qhi[i]);
            pe[t] = pn;
            oe[t] = ang;
            a->success[t] = (uint8_t)ok;
        }
    }
}

static void DK(solve_chunk)(const DK(Solve) *S, DK(Scratch) *sc, real *ul, DK(LMWork) *w, DK(Chunk) *c,
                            int64_t t0, int64_t t1) {
    c->t0 = c->next = t0;
    c->t1 = t1;
    memset(c->done, 0, CHUNK);
    memset(ul, 0, sizeof(real) * (size_t)S->n * W);
    for (int l = 0; l < W; l++) {
        c->prev[l] = -1;
        DK(refill)(S, c, ul, l, -1);
    }
    for (;;) {
        int any = 0;
        for (int l = 0; l < W; l++) any |= c->t[l] >= 0;
        if (!any) break;
        DK(chunk_step)(S, c, sc, ul, w);
    }
    DK(final_check)(S, sc, t0, t1, w->e1);
}

static int DK(solve_read)(const dk_args *chain, const dk_solve_args *a, DK(Solve) *S) {
    read_shape(chain, &S->s);
    if (DK(read_params)(chain, &S->s, &S->pp)) return -1;
    S->a = a;
    S->K = S->s.K;
    S->n = S->s.n;
    S->nv = S->s.nv;
    S->pos_only = a->xd == NULL;
    S->r = (S->pos_only ? 3 : 6) * S->K;
    S->d = S->r <= S->nv ? S->r : S->nv;
    S->N = a->n_targets, S->S = a->n_user, S->L = a->n_lib, S->P = a->n_pool;
    S->ts = a->target_stride > 0 ? a->target_stride : a->n_targets;
    S->R = a->lib_ranks < a->n_lib ? a->lib_ranks : a->n_lib;
    if (S->K > MAX_ENDS) S->R = 0;
    S->nseeds = a->n_seeds, S->maxit = a->max_iterations, S->minit = a->min_seed_iterations;
    S->every = a->iters > 0 ? a->iters : 1;
    S->tp = (real)a->tol_p, S->to = (real)a->tol_o, S->margin = (real)a->margin;
    S->damping2 = (real)a->damping2, S->mu = (real)a->error_damping, S->stall = (real)a->stall_ratio;
    S->w2 = (real)a->feature_weight;
    S->pd = (const real *)a->pd, S->xd = (const real *)a->xd, S->yd = (const real *)a->yd;
    S->zd = (const real *)a->zd, S->sqrt_w = (const real *)a->sqrt_w, S->jc = (const real *)a->jc;
    S->jh = (const real *)a->jh, S->user_u = (const real *)a->user_u, S->lib_u = (const real *)a->lib_u;
    S->lib_pose = (const real *)a->lib_pose, S->pool = (const real *)a->pool;
    S->qlo = (const real *)a->qlo, S->qhi = (const real *)a->qhi;
    S->bounded = a->bounded, S->wrap = a->wrap;
    S->stream = NULL;
    S->best_merit = (real *)malloc(sizeof(real) * (size_t)(S->N > 0 ? S->N : 1));
    S->sp.vq = NULL;
    if (!S->best_merit || space_read(&S->s, &S->sp) || support_read(&S->s, &S->sup)) {
        free(S->best_merit);
        free(S->pp.fix);
        free(S->sp.vq);
        return -1;
    }
    for (int64_t t = 0; t < S->N; t++) {
        S->best_merit[t] = (real)INFINITY;
        a->iters_out[t] = a->seeds_out[t] = 0;
    }
    return 0;
}

/* One thread's share of a solve: its scratch in buf, then chunks of CHUNK targets (all of them alone;
 * `shared`: the chunks of an orphaned omp for, dynamically scheduled over the enclosing team). */
static void DK(solve_worker)(const DK(Solve) *S, real *buf, int64_t nchunks, int shared) {
    const int n = S->n, nv = S->nv, r = S->r, d = S->d, R = (int)(S->R > 0 ? S->R : 1);
    const size_t base = DK(scratch_size)(&S->s) / sizeof(real);
    DK(Scratch) sc;
    DK(scratch_init)(&S->s, &S->pp, buf, &sc);
    real *ul = buf + base;
    DK(LMWork) w;
    w.dqdu = ul + (size_t)n * W;
    w.Jw = w.dqdu + (size_t)n * W;
    w.e = w.Jw + (size_t)r * nv * W;
    w.A = w.e + (size_t)r * W;
    w.y = w.A + (size_t)d * d * W;
    w.delta = w.y + (size_t)d * W;
    w.lam = w.delta + (size_t)nv * W;
    w.e1 = w.lam + W;
    DK(Chunk) c;
    c.nn = (int32_t *)(w.e1 + r);
    w.lanes = c.nn + CHUNK * R;
    c.done = (uint8_t *)(w.lanes + W);
    if (shared) {
#pragma omp for schedule(dynamic, 1)
        for (int64_t k = 0; k < nchunks; k++)
            DK(solve_chunk)(S, &sc, ul, &w, &c, k * CHUNK, k * CHUNK + CHUNK < S->N ? k * CHUNK + CHUNK : S->N);
    } else {
        for (int64_t k = 0; k < nchunks; k++)
            DK(solve_chunk)(S, &sc, ul, &w, &c, k * CHUNK, k * CHUNK + CHUNK < S->N ? k * CHUNK + CHUNK : S->N);
    }
}

/* Every target of the call (see the top of this file), the pool from `stream` when not NULL; returns 0, or
 * -1 when memory ran out. */
static int64_t DK(solve_from)(const dk_args *chain, const dk_solve_args *a, dk_stream *stream) {
    DK(Solve) S;
    if (a->lib_ranks > MAX_RANKS) return DK_RANGE_ERROR; /* no silent clamp: the caller asked for more */
    if (DK(solve_read)(chain, a, &S)) return -1;
    S.stream = stream;
    const int n = S.n, nv = S.nv, r = S.r, d = S.d, R = (int)(S.R > 0 ? S.R : 1);
    const int64_t nchunks = (S.N + CHUNK - 1) / CHUNK;
    int nthreads = (int)a->nthreads;
    if (nthreads < 1 || nchunks < 2) nthreads = 1;
    const size_t base = DK(scratch_size)(&S.s) / sizeof(real);
    const size_t lanes = (size_t)W * ((size_t)r * nv + r + (size_t)d * d + d + nv + 1); /* LMWork's */
    size_t per = 0;
    const size_t want = base + 2 * (size_t)n * W + lanes + r +
                        (sizeof(int32_t) * (CHUNK * (size_t)R + CHUNK + W) + CHUNK) / sizeof(real) + 1;
    /* one thread: the calling thread's kept work space (a single-target solve paid more for allocating
     * and faulting in a fresh one than for its LM steps) */
    real *all = nthreads == 1 ? (real *)kept_space(sizeof(real) * want) : DK(team_alloc)(want, nthreads, &per);
    if (!all) { free(S.pp.fix); free(S.best_merit); free(S.sp.vq); free(S.sup.cols); return -1; }
    if (nthreads == 1) { /* no team: OpenMP's fork and dynamic schedule cost a one-target call ~1 us */
        DK(solve_worker)(&S, all, nchunks, 0);
    } else {
#pragma omp parallel num_threads(nthreads)
        DK(solve_worker)(&S, all + per * (size_t)thread_id(), nchunks, 1);
    }
    if (nthreads > 1) free(all);
    free(S.pp.fix);
    free(S.best_merit);
    free(S.sp.vq);
    free(S.sup.cols);
    return 0;
}

/* The largest deviation from a rigid transform of N poses (4x4 row-major): max over |R^T R - I| entries and
 * |bottom row - (0 0 0 1)|; NaN when an entry is not finite. */
static double DK(rigid_deviation)(const real *T, int64_t N) {
    double worst = 0;
    for (int64_t b = 0; b < N; b++) {
        const real *M = T + b * 16;
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++) {
                double dot = 0;
                for (int k = 0; k < 3; k++) dot += (double)M[4 * k + i] * (double)M[4 * k + j];
                const double dev = fabs(dot - (i == j));
                worst = dev > worst ? dev : worst;
            }
        for (int j = 0; j < 4; j++) {
            const double dev = fabs((double)M[12 + j] - (j == 3));
            worst = dev > worst ? dev : worst;
        }
        for (int j = 0; j < 16; j++)
            if (!isfinite((double)M[j])) return NAN;
    }
    return worst;
}

static int64_t DK(dk_solve)(const dk_args *chain, const dk_solve_args *a) { return DK(solve_from)(chain, a, NULL); }

/* dk_solve_one (see _native.c): the pose T (4 x 4, row-major) checked rigid to 64 epsilon (the general
 * path's error otherwise: DK_NOT_RIGID, nothing solved), then the solve of tmpl with T as its one target
 * and the pool (pool_size uniforms: n_pool columns of nu) drawn here from `seed` (>= 0) or read from `pool`
 * (seed < 0). */
static int64_t DK(solve_one)(const dk_args *chain, const dk_solve_args *tmpl, const real *T, int64_t seed, const void *pool,
                             int64_t pool_size, void *q, void *ok, void *pe, void *oe, void *its, void *seeds) {
    const double exact = 64 * (sizeof(real) == 8 ? 0x1p-52 : 0x1p-23);
    if (!(DK(rigid_deviation)(T, 1) <= exact)) return DK_NOT_RIGID; /* NaN included */
    dk_solve_args a = *tmpl;
    a.xd = T, a.yd = T + 1, a.zd = T + 2, a.pd = T + 3; /* the pose's columns, rows 4 entries apart */
    a.pool = pool, a.q_out = q, a.success = ok, a.pos_err = pe, a.ori_err = oe, a.iters_out = its;
    a.seeds_out = seeds;
    if (seed < 0) return DK(solve_from)(chain, &a, NULL);
    static __thread real *buf;
    static __thread int64_t cap;
    if (pool_size > cap) { /* kept by the calling thread between calls, as the work space */
        free(buf);
        buf = (real *)malloc(sizeof(real) * (size_t)pool_size);
        cap = buf ? pool_size : 0;
        if (!buf) return -1;
    }
    dk_stream g;
    g.seeded = 0, g.seed = (uint64_t)seed, g.drawn = 0, g.buf = buf;
    return DK(solve_from)(chain, &a, &g);
}
