/* The whole of diffkin.ik.solve in one C call (included by _native.c once per real type, like its second
 * half): seeding, the Levenberg-Marquardt iteration (3.59) of dk_lm, harvest, stall detection, re-seeding
 * and the final check, for chains of 1-DOF joints. diffkin/ik/_native_solve.py prepares the arrays.
 *
 * Work is split into chunks of CHUNK targets, each solved by one thread on the W lanes of DK(block): a lane
 * holds one (target, seed) row. After every LM step a converged row is harvested (its target is done and
 * every other row of it retired); every `iters` steps a row older than min_seed_iterations whose merit did
 * not shrink by stall_ratio, or one at max_iterations, is finished (the best finished seed of each target is
 * kept). A free lane takes, after each step, in this order: the next seed of its last target, a user
 * seed not yet started of an open target (they run side by side, as in the torch loop), the first seed of
 * the chunk's next target, the next seed of the open target with the fewest rows among those that ran a
 * check interval (min_seed_iterations in a chunk of one target: an easy single target runs on one lane,
 * whose step costs a third of sixteen). A chunk's result depends only on its targets and
 * the inputs, so the solve is the same for every thread count and schedule.
 *
 * Seed s of target t: s < S the user's seed (t, s); s < S + R the library configuration with the (s - S)-th
 * nearest pose (squared distance of positions plus feature_weight times that of the rotation columns); else
 * column (t n_seeds + s) mod P of the pool of uniform draws, mapped to u uniform in q (u = asin((2r - 1)
 * (1 - 1e-6)) on bounded joints, lo + 2 h r on the others, as JointMap.sample_u).
 *
 * The result q = c + h sin(u) (bounded), wrapped by 2 pi towards the centre on revolute variables, clamped
 * into [qlo, qhi] when clamp; its exact errors come from one more FK; success = errors within the tolerances
 * (not the margin) and, when clamp, q within [qlo, qhi].
 */
#ifndef DK_SOLVE_ONCE_TYPES
#define DK_SOLVE_ONCE_TYPES
#define CHUNK 128 /* targets per chunk: a fixed number, so the answers do not depend on the thread count */
#define MAX_RANKS 64
#define MAX_ENDS 64 /* end links the nearest-pose search takes (more: no library seeds) */
#endif

/* q and dq/du of the W lanes of u (n x W, lane-major): q = c + h sin(u) on bounded joints, else q = u. */
static void DK(map_u)(int n, const uint8_t *bounded, const real *jc, const real *jh, const real *ul,
                      real *ql, real *dl) {
    for (int i = 0; i < n; i++) {
        double uu[W], sn[W], cs[W];
        const real *ui = ul + (size_t)i * W;
        real *qi = ql + (size_t)i * W, *di = dl + (size_t)i * W;
        if (!bounded[i]) {
            for (int l = 0; l < W; l++) { qi[l] = ui[l]; di[l] = 1; }
            continue;
        }
        for (int l = 0; l < W; l++) uu[l] = (double)ui[l];
        sincos_lanes(uu, sn, cs);
        for (int l = 0; l < W; l++) {
            qi[l] = jc[i] + jh[i] * (real)sn[l];
            di[l] = jh[i] * (real)cs[l];
        }
    }
}

/* The configuration update u <- u (+) delta of lane l (u lane-major, n x W): the one place a step is
 * applied, so that joints with another configuration space (ball, free) plug in here. */
static void DK(integrate)(int n, real *ul, int l, const real *delta) {
    for (int i = 0; i < n; i++) ul[(size_t)i * W + l] += delta[i];
}

typedef struct { /* the fixed inputs of a solve, read once */
    const dk_args *a;
    Shape s;
    DK(Params) pp;
    int K, n, r, d, pos_only;
    int64_t N, S, L, R, P, nseeds, maxit, minit, every;
    real tp, to, margin, damping2, mu, stall, w2;
    const real *pd, *xd, *yd, *zd, *sqrt_w, *jc, *jh, *user_u, *lib_u, *lib_pose, *pool, *qlo, *qhi;
    const uint8_t *bounded, *wrap;
    real *best_merit; /* [N] */
} DK(Solve);

/* The error e (r rows: [p_d - p_e; theta r] per end link, or p_d - p_e) of lane l against target t, its
 * worst position error *pn and angle *ang (the rotation-vector error of dk_lm). */
static void DK(lane_error)(const DK(Solve) *S, const real *ends, int l, int64_t t, real *e, real *pn,
                           real *ang) {
    const int64_t N = S->N;
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

/* The LM work space of a thread, lane-major (W lanes innermost): dqdu n, Jw r x n, e r, A d x d, y d,
 * delta n, inv d (reciprocal pivots), lam 1, each times W. */
typedef struct { real *dqdu, *Jw, *e, *A, *y, *delta, *inv, *lam; } DK(LMWork);

/* Cholesky solve A x = b in place for the lanes l0 .. l1 - 1 of a lane-major SPD A (d x d x W, its lower
 * triangle read and overwritten by the factor; b d x W): spd_solve's algorithm with the lane loop innermost,
 * so each line is one vector operation over the lanes. */
static void DK(spd_solve_lanes)(real *A, real *b, real *inv, int d, int l0, int l1) {
    const real tiny = (real)sqrt((double)DK_TINY);
#define AL(i, k) (A + ((size_t)(i) * d + (k)) * W)
    for (int j = 0; j < d; j++) {
        real *ajj = AL(j, j), *ij = inv + (size_t)j * W;
        for (int k = 0; k < j; k++) {
            const real *ajk = AL(j, k);
            for (int l = l0; l < l1; l++) ajj[l] -= ajk[l] * ajk[l];
        }
        for (int l = l0; l < l1; l++) {
            ajj[l] = (real)sqrt((double)(ajj[l] > tiny ? ajj[l] : tiny));
            ij[l] = 1 / ajj[l];
        }
        for (int i = j + 1; i < d; i++) {
            real *aij = AL(i, j);
            for (int k = 0; k < j; k++) {
                const real *aik = AL(i, k), *ajk = AL(j, k);
                for (int l = l0; l < l1; l++) aij[l] -= aik[l] * ajk[l];
            }
            for (int l = l0; l < l1; l++) aij[l] *= ij[l];
        }
    }
    for (int i = 0; i < d; i++) { /* L y = b */
        real *bi = b + (size_t)i * W;
        for (int k = 0; k < i; k++) {
            const real *aik = AL(i, k), *bk = b + (size_t)k * W;
            for (int l = l0; l < l1; l++) bi[l] -= aik[l] * bk[l];
        }
        for (int l = l0; l < l1; l++) bi[l] *= inv[(size_t)i * W + l];
    }
    for (int i = d - 1; i >= 0; i--) { /* L^T x = y */
        real *bi = b + (size_t)i * W;
        for (int k = i + 1; k < d; k++) {
            const real *aki = AL(k, i), *bk = b + (size_t)k * W;
            for (int l = l0; l < l1; l++) bi[l] -= aki[l] * bk[l];
        }
        for (int l = l0; l < l1; l++) bi[l] *= inv[(size_t)i * W + l];
    }
#undef AL
}

/* The damped least-squares step (3.59) of lanes l0 .. l1 - 1 on their errors e (r x W, weighted in place):
 * delta = J_w^T (J_w J_w^T + lambda I)^-1 e_w (or the n x n normal equations when r > n), lambda =
 * damping2 + mu |e_w|^2, J_w = diag(sqrt_w) J diag(dq/du). All lanes of the range at once, lane-major: as
 * one scalar lane at a time the inner products reduced horizontally and this step was over half of a
 * batched solve's time. A lane of the range that takes no step computes values nobody reads. */
static void DK(lanes_delta)(const DK(Solve) *S, const real *Jb, int l0, int l1, DK(LMWork) *w) {
    const int n = S->n, r = S->r, d = S->d, rows = S->pos_only ? 3 : 6;
    real *e = w->e, *Jw = w->Jw, *A = w->A, *y = w->y, *delta = w->delta, *lam = w->lam;
    for (int l = l0; l < l1; l++) lam[l] = 0;
    for (int a = 0; a < r; a++) {
        real *ea = e + (size_t)a * W;
        const real sw = S->sqrt_w[a];
        for (int l = l0; l < l1; l++) {
            ea[l] *= sw;
            lam[l] += ea[l] * ea[l];
        }
    }
    for (int l = l0; l < l1; l++) lam[l] = S->damping2 + S->mu * lam[l];
    for (int k = 0; k < S->K; k++)
        for (int a = 0; a < rows; a++)
            for (int i = 0; i < n; i++) {
                const real *jb = Jb + ((size_t)k * 6 * n + (size_t)a * n + i) * W, *dq = w->dqdu + (size_t)i * W;
                const real sw = S->sqrt_w[rows * k + a];
                real *jw = Jw + ((size_t)(rows * k + a) * n + i) * W;
                for (int l = l0; l < l1; l++) jw[l] = jb[l] * sw * dq[l];
            }
#define JW(a, i) (Jw + ((size_t)(a) * n + (i)) * W)
    if (r <= n) {
        for (int a = 0; a < r; a++) {
            for (int c = 0; c <= a; c++) { /* the lower triangle: all the factorisation reads */
                real *acc = A + ((size_t)a * d + c) * W;
                for (int l = l0; l < l1; l++) acc[l] = 0;
                for (int i = 0; i < n; i++) {
                    const real *ja = JW(a, i), *jc = JW(c, i);
                    for (int l = l0; l < l1; l++) acc[l] += ja[l] * jc[l];
                }
            }
            real *aa = A + ((size_t)a * d + a) * W, *ya = y + (size_t)a * W, *ea = e + (size_t)a * W;
            for (int l = l0; l < l1; l++) {
                aa[l] += lam[l];
                ya[l] = ea[l];
            }
        }
        DK(spd_solve_lanes)(A, y, w->inv, d, l0, l1);
        for (int i = 0; i < n; i++) {
            real *di = delta + (size_t)i * W;
            for (int l = l0; l < l1; l++) di[l] = 0;
            for (int a = 0; a < r; a++) {
                const real *ja = JW(a, i), *ya = y + (size_t)a * W;
                for (int l = l0; l < l1; l++) di[l] += ja[l] * ya[l];
            }
        }
        return;
    }
    for (int i = 0; i < n; i++) {
        for (int c = 0; c <= i; c++) {
            real *acc = A + ((size_t)i * d + c) * W;
            for (int l = l0; l < l1; l++) acc[l] = 0;
            for (int a = 0; a < r; a++) {
                const real *ji = JW(a, i), *jc = JW(a, c);
                for (int l = l0; l < l1; l++) acc[l] += ji[l] * jc[l];
            }
        }
        real *di = delta + (size_t)i * W, *ai = A + ((size_t)i * d + i) * W;
        for (int l = l0; l < l1; l++) di[l] = 0;
        for (int a = 0; a < r; a++) {
            const real *ji = JW(a, i), *ea = e + (size_t)a * W;
            for (int l = l0; l < l1; l++) di[l] += ji[l] * ea[l];
        }
        for (int l = l0; l < l1; l++) ai[l] += lam[l];
    }
#undef JW
    DK(spd_solve_lanes)(A, delta, w->inv, d, l0, l1);
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
        ft[c] = tcol[c / K3][(int64_t)(c % K3) * S->N + t];
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
    const real *r = S->pool + (size_t)((t * S->nseeds + s) % S->P) * n;
    for (int i = 0; i < n; i++) {
        const real v = S->bounded[i] ? (real)asin((double)((2 * r[i] - 1) * (real)(1.0 - 1e-6)))
                                     : (S->jc[i] - S->jh[i]) + 2 * S->jh[i] * r[i];
        ul[(size_t)i * W + l] = v;
    }
}

typedef struct { /* the rows of one chunk: per lane (t < 0: free; prev: its last target) and per target */
    int64_t t0, t1, next, t[W], it[W], prev[W];
    real last[W];
    int32_t *nn, *count; /* [CHUNK * R], [CHUNK] */
    uint8_t *done;       /* [CHUNK] */
} DK(Chunk);

/* Start a seed of target t in lane l (nothing when t has no seeds left); returns whether it did. */
static int DK(start)(const DK(Solve) *S, DK(Chunk) *c, int64_t t, real *ul, int l) {
    int64_t *seeds = S->a->seeds_out;
    const int64_t j = t - c->t0;
    if (t < 0 || c->done[j] || seeds[t] >= S->nseeds) return 0;
    if (seeds[t] == 0 && S->R) DK(nearest)(S, t, c->nn + j * S->R);
    DK(seed)(S, t, seeds[t], c->nn + j * S->R, ul, l);
    if (seeds[t] == 0) /* a first best: every target ends with some u */
        for (int i = 0; i < S->n; i++) ((real *)S->a->q_out)[t * S->n + i] = ul[(size_t)i * W + l];
    seeds[t]++;
    c->count[j]++;
    c->t[l] = t;
    c->it[l] = 0;
    c->last[l] = (real)INFINITY;
    return 1;
}

/* Give a free lane l work: the next seed of its last target, a user seed not yet started, a new target,
 * or the next seed of the open target with the fewest rows among those that ran a check interval (as the
 * torch loop's top-up, which follows a round: a target converging at its first evaluation has tried one
 * seed), min_seed_iterations when the chunk holds one target. */
static void DK(refill)(const DK(Solve) *S, DK(Chunk) *c, real *ul, int l, int64_t last) {
    c->t[l] = -1;
    if (DK(start)(S, c, last, ul, l)) return;
    for (int64_t t = c->t0; t < c->next; t++) /* the user's seeds of an open target run side by side */
        if (S->a->seeds_out[t] < S->S && DK(start)(S, c, t, ul, l)) return;
    while (c->next < c->t1)
        if (DK(start)(S, c, c->next++, ul, l)) return;
    int64_t pick = -1;
    for (int64_t t = c->t0; t < c->t1; t++) {
        const int64_t j = t - c->t0;
        if (c->count[j] > 0 && !c->done[j] && S->a->seeds_out[t] < S->nseeds &&
            S->a->iters_out[t] >= (c->t1 - c->t0 > 1 ? S->every : S->minit) &&
            (pick < 0 || c->count[j] < c->count[pick - c->t0]))
            pick = t;
    }
    DK(start)(S, c, pick, ul, l);
}

/* Lane l's row ends: it converged (keep u, retire the target's other rows) or was finished with merit
 * (keep u if the target's best so far); the lane is refilled after the step. */
static void DK(finish)(const DK(Solve) *S, DK(Chunk) *c, real *ul, int l, int conv, real merit) {
    const int64_t t = c->t[l], j = t - c->t0;
    real *best = (real *)S->a->q_out + t * S->n;
    if (conv || merit <= S->best_merit[t]) {
        S->best_merit[t] = conv ? -1 : merit;
        for (int i = 0; i < S->n; i++) best[i] = ul[(size_t)i * W + l];
    }
    c->count[j]--;
    if (conv) {
        c->done[j] = 1;
        for (int o = 0; o < W; o++)
            if (o != l && c->t[o] == t) { c->count[j]--; c->t[o] = -1; }
    }
    c->t[l] = -1;
    c->prev[l] = t;
}

/* One LM step on the chunk's lanes, with harvest and stall checks. */
static void DK(chunk_step)(const DK(Solve) *S, DK(Chunk) *c, DK(Scratch) *sc, real *ul, DK(LMWork) *w) {
    DK(map_u)(S->n, S->bounded, S->jc, S->jh, ul, sc->qlanes, w->dqdu);
    DK(block)(&S->s, &S->pp, sc, 1);
    int64_t *iters = S->a->iters_out;
    int l0 = W, l1 = 0; /* the lanes that take a step lie in l0 .. l1 - 1 */
    for (int l = 0; l < W; l++) {
        const int64_t t = c->t[l];
        if (t < 0) continue;
        real pn, ang, el[S->r]; /* this lane's error, then scattered into the lanes' e */
        DK(lane_error)(S, sc->ends, l, t, el, &pn, &ang);
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
        for (int a = 0; a < S->r; a++) w->e[(size_t)a * W + l] = el[a];
        l0 = l < l0 ? l : l0;
        l1 = l + 1;
    }
    if (l1 > l0) DK(lanes_delta)(S, sc->Jb, l0, l1, w);
    for (int l = l0; l < l1; l++) { /* the rows still running (a converged row retires its target's others) */
        if (c->t[l] < 0) continue;
        real dl[S->n];
        for (int i = 0; i < S->n; i++) dl[i] = w->delta[(size_t)i * W + l];
        DK(integrate)(S->n, ul, l, dl);
    }
    for (int l = 0; l < W; l++) /* after every row's checks: only targets still open take lanes */
        if (c->t[l] < 0) {
            DK(refill)(S, c, ul, l, c->prev[l]);
            c->prev[l] = -1;
        }
}

/* The final q of targets t0 .. t1 - 1 (their best u in q_out, replaced) and its exact check. */
static void DK(final_check)(const DK(Solve) *S, DK(Scratch) *sc, int64_t t0, int64_t t1, real *e) {
    const dk_args *a = S->a;
    const int n = S->n;
    real *q = (real *)a->q_out, *pe = (real *)a->pos_err, *oe = (real *)a->ori_err;
    const double two_pi = 6.283185307179586;
    for (int64_t b0 = t0; b0 < t1; b0 += W) {
        const int nl = (int)(t1 - b0 < W ? t1 - b0 : W);
        for (int l = 0; l < W; l++) {
            real *qt = q + (b0 + (l < nl ? l : nl - 1)) * n;
            for (int i = 0; i < n && l < nl; i++) {
                double v = S->bounded[i] ? (double)S->jc[i] + (double)S->jh[i] * sin((double)qt[i]) : qt[i];
                if (S->wrap[i]) v -= two_pi * nearbyint((v - (double)S->jc[i]) / two_pi);
                if (a->clamp) v = v < S->qlo[i] ? S->qlo[i] : (v > S->qhi[i] ? S->qhi[i] : v);
                qt[i] = (real)v;
            }
            for (int i = 0; i < n; i++) sc->qlanes[(size_t)i * W + l] = qt[i];
        }
        DK(block)(&S->s, &S->pp, sc, 0);
        for (int l = 0; l < nl; l++) {
            const int64_t t = b0 + l;
            real pn, ang;
            DK(lane_error)(S, sc->ends, l, t, e, &pn, &ang);
            int ok = pn <= S->tp && (S->pos_only || ang <= S->to);
            for (int i = 0; i < n && a->clamp; i++) ok &= q[t * n + i] >= S->qlo[i] && q[t * n + i] <= S->qhi[i];
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
    memset(c->count, 0, sizeof(int32_t) * CHUNK);
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
    DK(final_check)(S, sc, t0, t1, w->e);
}

static int DK(solve_read)(const dk_args *a, DK(Solve) *S) {
    read_shape(a, &S->s);
    if (DK(read_params)(a, &S->s, &S->pp)) return -1;
    S->a = a;
    S->K = S->s.K;
    S->n = S->s.n;
    S->pos_only = a->xd == NULL;
    S->r = (S->pos_only ? 3 : 6) * S->K;
    S->d = S->r <= S->n ? S->r : S->n;
    S->N = a->n_targets, S->S = a->n_user, S->L = a->n_lib, S->P = a->n_pool;
    S->R = a->lib_ranks < a->n_lib ? a->lib_ranks : a->n_lib;
    S->R = S->R < MAX_RANKS ? S->R : MAX_RANKS;
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
    S->best_merit = (real *)malloc(sizeof(real) * (size_t)(S->N > 0 ? S->N : 1));
    if (!S->best_merit) { free(S->pp.fix); return -1; }
    for (int64_t t = 0; t < S->N; t++) {
        S->best_merit[t] = (real)INFINITY;
        a->iters_out[t] = a->seeds_out[t] = 0;
    }
    return 0;
}

/* Every target of the call (see the top of this file); returns 0, or -1 when memory ran out. */
static int64_t DK(dk_solve)(const dk_args *a) {
    DK(Solve) S;
    if (DK(solve_read)(a, &S)) return -1;
    const int n = S.n, r = S.r, d = S.d, R = (int)(S.R > 0 ? S.R : 1);
    const int64_t nchunks = (S.N + CHUNK - 1) / CHUNK;
    int nthreads = (int)a->nthreads;
    if (nthreads < 1 || nchunks < 2) nthreads = 1;
    const size_t base = DK(scratch_size)(&S.s) / sizeof(real);
    const size_t lm = ((size_t)n + (size_t)r * n + r + (size_t)d * d + 2 * (size_t)d + n + 1) * W; /* LMWork */
    const size_t per = base + (size_t)n * W + lm +
                       (sizeof(int32_t) * (CHUNK * (size_t)R + CHUNK) + CHUNK) / sizeof(real) + 1;
    real *all = (real *)malloc(sizeof(real) * per * (size_t)nthreads);
    if (!all) { free(S.pp.fix); free(S.best_merit); return -1; }
#pragma omp parallel num_threads(nthreads) if (nthreads > 1)
    {
        real *buf = all + per * (size_t)thread_id();
        DK(Scratch) sc;
        DK(scratch_init)(&S.s, &S.pp, buf, &sc);
        real *ul = buf + base;
        DK(LMWork) w;
        w.dqdu = ul + (size_t)n * W;
        w.Jw = w.dqdu + (size_t)n * W;
        w.e = w.Jw + (size_t)r * n * W;
        w.A = w.e + (size_t)r * W;
        w.y = w.A + (size_t)d * d * W;
        w.delta = w.y + (size_t)d * W;
        w.inv = w.delta + (size_t)n * W;
        w.lam = w.inv + (size_t)d * W;
        DK(Chunk) c;
        c.nn = (int32_t *)(w.lam + W);
        c.count = c.nn + CHUNK * R;
        c.done = (uint8_t *)(c.count + CHUNK);
#pragma omp for schedule(dynamic, 1)
        for (int64_t k = 0; k < nchunks; k++) {
            const int64_t t0 = k * CHUNK, t1 = t0 + CHUNK < S.N ? t0 + CHUNK : S.N;
            DK(solve_chunk)(&S, &sc, ul, &w, &c, t0, t1);
        }
    }
    free(all);
    free(S.pp.fix);
    free(S.best_merit);
    return 0;
}

/* See dk_rigid_deviation. */
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
