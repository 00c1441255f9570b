/* TOPP-RA (diffkin/trajectories/time_optimal.py, _topp) and the timing's dense check and samples for CPU tensors
 * without autograd (included by _native.c once per real type, like _native_banded.c). From the path's
 * derivatives at the grid (topp_grid), every constraint row but the moving one is reduced before the passes;
 * the passes meet, per grid interval i of a path,
 *
 *     backward: kn_i = min(K_{i+1}, xq_i),  K_i = min(fixed_i, max(0, min_r (Aq_ir kn_i + G_ir) / C_ir))
 *     forward:  x_i = min(x_i, K_i),  u = max(min(min_r (Gu_ir - Bu_ir x_i) / Au_ir, (kn_i - x_i) / d_i),
 *               -x_i / d_i),  x_{i+1} = min(max(x_i + d_i u, 0), K_{i+1})
 *
 * with K_{M-1} = 0 and x_0 = 0: one grid point after another, a few flops each, which torch spends one
 * operator call on (most of the time of a short batch). The same operations in the same order as the torch
 * loop, each a statement of its own and never contracted into a fused multiply-add (_native.c includes this
 * file with contraction off), and the minima and maxima propagate NaN as torch.minimum / amin / clamp do: the
 * same floats. Paths are shared between threads. */

/* One path: Aq, G, C (M - 1, R); Au, Bu, Gu (M - 1, Ru); fixed, xq, d (M - 1); K (M), Kn (M - 1) work;
 * x (M) out. */
static void DK(topp_path)(const real *Aq, const real *G, const real *C, const real *Au, const real *Bu,
                          const real *Gu, const real *fixed, const real *xq, const real *d, int64_t M,
                          int64_t R, int64_t Ru, real *K, real *Kn, real *x) {
    K[M - 1] = 0;
    for (int64_t i = M - 2; i >= 0; i--) {
        const real kn = DK(nan_min)(K[i + 1], xq[i]);
        Kn[i] = kn;
        real moving = (real)INFINITY;
        for (int64_t r = 0; r < R; r++) {
            real v = Aq[i * R + r] * kn;
            v = v + G[i * R + r];
            v = v / C[i * R + r];
            moving = DK(nan_min)(moving, v);
        }
        K[i] = DK(nan_min)(fixed[i], DK(nan_max)(moving, 0));
    }
    x[0] = 0;
    for (int64_t i = 0; i < M - 1; i++) {
        const real xi = DK(nan_min)(x[i], K[i]);
        x[i] = xi;
        real up = (real)INFINITY;
        for (int64_t r = 0; r < Ru; r++) {
            real v = Bu[i * Ru + r] * xi;
            v = Gu[i * Ru + r] - v;
            v = v / Au[i * Ru + r];
            up = DK(nan_min)(up, v);
        }
        real next = Kn[i] - xi;
        next = next / d[i];
        real u = DK(nan_min)(up, next);
        const real low = -xi / d[i];
        u = DK(nan_max)(u, low);
        real step = d[i] * u;
        step = xi + step;
        x[i + 1] = DK(nan_min)(DK(nan_max)(step, 0), K[i + 1]);
    }
}

/* The bound on x = ṡ² of one grid interval from its fixed rows (time_optimal._max_x: Fourier–Motzkin on u over
 * every pair of an upper row p (α_p > 0) and a lower row q: the acceleration rows' partners and u ≥ −x / 2Δ),
 * from its upper rows a, b, g (R each, R = 2n), the rows without u (alone), Δ and the velocity bound xv; the
 * pairs in registers instead of torch's (I, R, R + 1) temporaries. */
static inline real DK(fixed_bound)(const real *a, const real *b, const real *g, int64_t R, real alone, real delta,
                                   real xv) {
    const real d2 = 2 * delta;
    real bound = (real)INFINITY;
    for (int64_t p = 0; p < R; p++) {
        if (!(a[p] > 0)) continue;
        const real Ap = a[p];
        for (int64_t q = 0; q <= R; q++) {
            const real Aq = q < R ? a[q] : d2;
            if (!(Aq > 0)) continue;
            const real bq = q < R ? -b[q] : -1;
            const real gq = q < R ? g[q] : 0;
            real c = Ap * bq;
            real w = Aq * b[p];
            c = c + w;
            if (!(c > 0)) continue;
            real d = Aq * g[p];
            w = Ap * gq;
            d = d + w;
            bound = DK(nan_min)(bound, d / c);
        }
    }
    real r = DK(nan_min)(bound, alone);
    r = r < 0 ? 0 : r;  /* clamp_min(0) keeps a NaN */
    return DK(nan_min)(r, xv);
}

/* The speed bound min_j (v_j / max(|q'_j|, 1e-300))² over the joints with q'_j ≠ 0 (big where none). */
static inline real DK(speed_bound)(const real *d1, const real *vmax, int64_t n, real big) {
    real x = (real)INFINITY;
    for (int64_t j = 0; j < n; j++) {
        const real m = fabs(d1[j]);
        real y = m < (real)1e-300 ? (real)1e-300 : m;  /* clamp_min keeps a NaN */
        y = vmax[j] / y;
        y = y * y;
        x = DK(nan_min)(x, m > 0 ? y : big);
    }
    return x;
}

/* The whole of time_optimal._topp after the path's derivatives, per path: from P1, P2 (M, n) at the grid points
 * (right-hand), Q1, Q2 (M - 1, n) at the interval ends (left-hand), amax, vmax (n), Δ (M - 1) and stops (M,
 * 1 where ṡ = 0): the rows of each interval (_rows), their fixed bound (fixed_bound), the moving row's terms
 * and the passes (topp_path), x (M) out; big: _X_BIG. The same operations in the same order as the torch code:
 * the same floats. Returns -1 when the work space cannot be allocated. */
static int64_t DK(topp_grid)(const real *P1, const real *P2, const real *Q1, const real *Q2, const real *amax,
                             const real *vmax, const real *delta, const real *stops, real *x, int64_t B, int64_t M,
                             int64_t n, real big, int64_t nthreads) {
    const int64_t R = 2 * n + 1, Ru = 2 * n, I = M - 1;
    int64_t status = 0;
#pragma omp parallel for num_threads(nthreads) schedule(dynamic, 1)
    for (int64_t b = 0; b < B; b++) {
        real *w = (real *)malloc(sizeof(real) * (size_t)(I * (3 * R + 3 * Ru + 4) + M + 3 * Ru));
        if (!w) {
#pragma omp atomic write
            status = -1;
            continue;
        }
        real *Aq = w, *G = Aq + I * R, *C = G + I * R, *Au = C + I * R, *Bu = Au + I * Ru, *Gu = Bu + I * Ru;
        real *fixed = Gu + I * Ru, *xq = fixed + I, *d = xq + I, *Kn = d + I, *K = Kn + I;
        real *al = K + M, *be = al + Ru, *ga = be + Ru;
        const real *p1 = P1 + b * M * n, *p2 = P2 + b * M * n, *q1 = Q1 + b * I * n, *q2 = Q2 + b * I * n;
        const real *am = amax + b * n, *vm = vmax + b * n, *dl = delta + b * I, *st = stops + b * M;
        for (int64_t i = 0; i < I; i++) {
            const real di = dl[i];
            const real d2 = 2 * di;
            for (int64_t j = 0; j < n; j++) {  /* _rows */
                const real P1j = p1[i * n + j], P2j = p2[i * n + j], Q1j = q1[i * n + j], Q2j = q2[i * n + j];
                real A = d2 * Q2j;
                A = Q1j + A;
                al[j] = fabs(P1j), al[n + j] = fabs(A);
                be[j] = P1j < 0 ? -P2j : P2j, be[n + j] = A < 0 ? -Q2j : Q2j;
                ga[j] = am[j], ga[n + j] = am[j];
            }
            real alone = (real)INFINITY;
            for (int64_t r = 0; r < Ru; r++)
                if (al[r] == 0 && be[r] != 0) alone = DK(nan_min)(alone, ga[r] / fabs(be[r]));
            real xv = DK(speed_bound)(p1 + i * n, vm, n, big);
            xv = DK(nan_min)(xv, big);
            xv = st[i] != 0 ? 0 : xv;
            xq[i] = DK(speed_bound)(q1 + i * n, vm, n, big);
            fixed[i] = DK(fixed_bound)(al, be, ga, Ru, alone, di, xv);
            d[i] = d2;
            /* the moving row with each lower row, and the fixed upper rows for u (the torch code's wheres) */
            for (int64_t q = 0; q < R; q++) {
                const int up = q < Ru && al[q] > 0;
                const real Aqq = q < Ru ? (up ? al[q] : 0) : d2;
                const real bq = q < Ru ? -be[q] : -1;
                const real gq = q < Ru ? ga[q] : 0;
                real c = d2 * bq;
                c = c + Aqq;
                const int pair = Aqq > 0 && c > 0;
                Aq[i * R + q] = pair ? Aqq : 0;
                G[i * R + q] = pair ? d2 * gq : (real)INFINITY;
                C[i * R + q] = pair ? c : 1;
                if (q < Ru) {
                    Au[i * Ru + q] = up ? al[q] : 1;
                    Bu[i * Ru + q] = up ? be[q] : 0;
                    Gu[i * Ru + q] = up ? ga[q] : (real)INFINITY;
                }
            }
        }
        DK(topp_path)(Aq, G, C, Au, Bu, Gu, fixed, xq, d, M, R, Ru, K, Kn, x + b * M);
        free(w);
    }
    return status;
}

/* The dense limit check of time_optimal (_peaks): per path the largest |q̇_j| / v_j, |q̈_j| / a_j (and |q⃛_j| / j_j
 * with nlim = 3) over the sample times t (B, T), of the profile smoothed by τ and stretched by k (TimedPath._joint:
 * _base twice, _profile, the path's Horner evaluation), each sample one pass through its own profile interval
 * and path segment: torch spends a full-size temporary on each of its ~100 steps. The same operations in the
 * same order as the torch code (x**2 and x**3 as x·x and x·x·x, as torch computes them), so the same floats:
 * the peaks are maxima of absolute values, so only a zero's sign could differ, which they do not show. */

/* torch.searchsorted(a[:L], x, right=True): the count of a's sorted values <= x (torch's upper bound). */
static inline int64_t DK(upper_bound)(const real *a, int64_t L, real x) {
    int64_t lo = 0, hi = L;
    while (lo < hi) {
        const int64_t mid = lo + ((hi - lo) >> 1);
        if (!(a[mid] > x)) lo = mid + 1;
        else hi = mid;
    }
    return lo;
}

/* upper_bound from the previous answer *h (a walk of at most a few steps: the samples come in time order
 * but for one jump back), else the binary search; a sorted array without NaN (sorted) has one answer, so
 * both give it. The answer is kept in *h. */
static inline int64_t DK(upper_bound_near)(const real *a, int64_t L, real x, int sorted, int64_t *h) {
    int64_t i = *h;
    if (sorted && x == x) {
        for (int step = 0; step < 4; step++) {
            if (i < L && !(a[i] > x)) i++;
            else if (i > 0 && a[i - 1] > x) i--;
            else return *h = i;
        }
    }
    return *h = DK(upper_bound)(a, L, x);
}

/* a[0..L) non-decreasing and free of NaN */
static inline int DK(sorted)(const real *a, int64_t L) {
    for (int64_t i = 0; i < L; i++)
        if (a[i] != a[i] || (i && a[i] < a[i - 1])) return 0;
    return 1;
}

/* TimedPath._base at time t of one path: s, ṡ, s̈ and ∫s (out[0..3]) of the unsmoothed profile, from its knot
 * times pt, grid points s, speeds sd, ∫s at the knots Sk (M) and accelerations u (M - 1); sorted, *h: pt's
 * (DK(upper_bound_near)). */
static inline void DK(profile_base)(const real *pt, const real *grid, const real *sd, const real *u,
                                    const real *Sk, int64_t M, real t, int sorted, int64_t *h, real *out) {
    const real T_end = pt[M - 1];
    real tc = t < 0 ? 0 : t;  /* clamp(min=0) keeps a NaN */
    tc = DK(nan_min)(tc, T_end);
    const int64_t i = DK(upper_bound_near)(pt + 1, M - 2, tc, sorted, h);
    const real d = tc - pt[i];
    const real s0 = grid[i], v0 = sd[i], ui = u[i];
    const real d2 = d * d;
    const real d3 = d2 * d;
    real s = v0 * d;
    s = s0 + s;
    real w = ui * d2;
    w = w / 2;
    s = s + w;
    real S = s0 * d;
    S = Sk[i] + S;
    w = v0 * d2;
    w = w / 2;
    S = S + w;
    w = ui * d3;
    w = w / 6;
    S = S + w;
    const int inside = (t >= 0) & (t <= T_end);
    if (t > T_end) {
        w = t - T_end;
        w = w * s;
        S = S + w;
    } else if (t < 0) {
        S = 0;
    }
    real v = ui * d;
    v = v0 + v;
    out[0] = s;
    out[1] = inside ? v : 0;
    out[2] = (inside && t < T_end) ? ui : 0;
    out[3] = S;
}

/* TimedPath._profile and the stretch of _joint at time t of one path (profile arrays as DK(profile_base), its
 * τ and k; sorted, h1, h2: DK(upper_bound_near) of the two base evaluations): s (clamped into [0, 1]), ṡ, s̈,
 * s⃛ of the smoothed, stretched law into out[0..3]. */
static inline void DK(law_at)(const real *pt, const real *grid, const real *sd, const real *u, const real *Sk,
                              int64_t M, real tau, real k, int sorted, int64_t *h1, int64_t *h2, real t,
                              real *out) {
    const int smooth = tau > 0, unit = k == 1;  /* x / 1 is x, bit for bit (the candidates' k) */
    const real taus = smooth ? tau : 1;
    const real tk = unit ? t : t / k;
    real b[4], b2[4];
    DK(profile_base)(pt, grid, sd, u, Sk, M, tk, sorted, h1, b);
    DK(profile_base)(pt, grid, sd, u, Sk, M, tk - taus, sorted, h2, b2);
    real sb, vb, ab, jb;
    if (smooth) {
        sb = b[3] - b2[3];
        sb = sb / taus;
        vb = b[0] - b2[0];
        vb = vb / taus;
        ab = b[1] - b2[1];
        ab = ab / taus;
        jb = b[2] - b2[2];
        jb = jb / taus;
    } else {
        sb = b[0], vb = b[1], ab = b[2], jb = 0;
    }
    const real done_at = pt[M - 1] + tau;
    if (tk >= done_at) sb = 1, vb = 0, ab = 0, jb = 0;
    if (unit) {
        out[1] = vb, out[2] = ab, out[3] = jb;
    } else {
        const real k2 = k * k;
        const real k3 = k2 * k;
        out[1] = vb / k, out[2] = ab / k2, out[3] = jb / k3;
    }
    real s = sb < 0 ? 0 : sb;  /* clamp(0, 1) keeps a NaN */
    out[0] = s > 1 ? 1 : s;
}

/* poly_eval from the top coefficient (c3, c2, c1, c0) at x: q, q', q'' into out[0..2]. */
static inline void DK(cubic_at)(real c0, real c1, real c2, real c3, real x, real *out) {
    real p = c3 * x;
    p = p + c2;
    real q1 = c3;
    real q2 = 2 * q1;
    real h = q1 * x;
    q1 = h + p;
    h = p * x;
    p = h + c1;
    q2 = q2 * x;
    h = 2 * q1;
    q2 = q2 + h;
    h = q1 * x;
    q1 = h + p;
    h = p * x;
    out[0] = h + c0;
    out[1] = q1;
    out[2] = q2;
}

/* A joint at path point x of its segment (coefficients c0..c3) moved at ṡ = v, s̈ = a (vv = ṡ²): q, q', q''
 * (DK(cubic_at)) into *q, *d1, *d2 and q̇ = q' ṡ, q̈ = q' s̈ + q'' ṡ² (TimedPath._joint's order) into *qd, *qdd. */
static inline void DK(joint_rates)(real c0, real c1, real c2, real c3, real x, real v, real a, real vv, real *q,
                                   real *d1, real *d2, real *qd, real *qdd) {
    real c[3];
    DK(cubic_at)(c0, c1, c2, c3, x, c);
    *q = c[0], *d1 = c[1], *d2 = c[2];
    *qd = c[1] * v;
    const real t = c[1] * a;
    const real h = c[2] * vv;
    *qdd = t + h;
}

/* _Path.eval's q' and q'' of B paths for time_optimal's grid (_topp): P1, P2 (B, M, n) at grid[m] on segment
 * kseg[m] (right-hand at a knot), Q1, Q2 (B, M - 1, n) at grid[m + 1] on segment kseg[m] (each interval's end,
 * left-hand); in: knots s (B, N), c0..c3 (B, N - 1, n), grid (B, M); DK(cubic_at)'s Horner: the same floats.
 * Paths are shared between threads. */
static int64_t DK(topp_slopes)(const real *const *in, const int64_t *kseg, real *P1, real *P2, real *Q1, real *Q2,
                               int64_t B, int64_t M, int64_t N, int64_t n, int64_t nthreads) {
#pragma omp parallel for num_threads(nthreads) schedule(dynamic, 1)
    for (int64_t b = 0; b < B; b++) {
        const real *s = in[0] + b * N, *grid = in[5] + b * M;
        const int64_t E = b * (N - 1) * n, *kb = kseg + b * M;
        for (int64_t m = 0; m < 2 * M - 1; m++) {
            const int end = m >= M; /* the second pass: the intervals' ends */
            const int64_t i = end ? m - M : m, k = kb[i];
            const real x = grid[end ? i + 1 : i] - s[k];
            real *d1 = end ? Q1 + (b * (M - 1) + i) * n : P1 + (b * M + i) * n;
            real *d2 = end ? Q2 + (b * (M - 1) + i) * n : P2 + (b * M + i) * n;
            const int64_t e = E + k * n;
            for (int64_t c = 0; c < n; c++) {
                real q[3];
                DK(cubic_at)(in[1][e + c], in[2][e + c], in[3][e + c], in[4][e + c], x, q);
                d1[c] = q[1];
                d2[c] = q[2];
            }
        }
    }
    return 0;
}

/* One path: prof = (pt, grid, sd, Sk (M), u (M - 1)), its τ and k; the geometric path's knots ps (N) and
 * coefficients c0..c3 (N - 1, n); lim (nlim, n); top (nlim, n) work; peak (nlim) out. Each joint's largest
 * |q̇_j| (|q̈_j|, |q⃛_j|) is divided by its limit once, at the end: a correctly rounded division is monotone in
 * its numerator, so that is the largest of the per-sample quotients, bit for bit. */
static void DK(peaks_path)(const real *t, int64_t T, const real *pt, const real *grid, const real *sd,
                           const real *u, const real *Sk, int64_t M, real tau, real k, const real *ps,
                           const real *c0, const real *c1, const real *c2, const real *c3, int64_t N, int64_t n,
                           const real *const *lim, int64_t nlim, real *top, real *peak) {
    for (int64_t e = 0; e < nlim * n; e++) top[e] = 0;
    const int pt_sorted = DK(sorted)(pt + 1, M - 2), ps_sorted = DK(sorted)(ps + 1, N - 2);
    int64_t h1 = 0, h2 = 0, hs = 0;
    real *top_v = top, *top_a = top + n, *top_j = top + 2 * n;
    for (int64_t m = 0; m < T; m++) {
        real law[4];
        DK(law_at)(pt, grid, sd, u, Sk, M, tau, k, pt_sorted, &h1, &h2, t[m], law);
        const real s = law[0], v = law[1], a = law[2], j = law[3];
        const int64_t g = DK(upper_bound_near)(ps + 1, N - 2, s, ps_sorted, &hs);
        const real x = s - ps[g];
        const real vv = v * v;
        const real vvv = vv * v;
        const int64_t e = g * n;
        const real *C0 = c0 + e, *C1 = c1 + e, *C2 = c2 + e, *C3 = c3 + e;
        /* the joints side by side (each lane the scalar statements below, in their order: the same floats) */
        if (nlim > 2) {
#pragma omp simd
            for (int64_t c = 0; c < n; c++) {
                real q, q1, q2, qd, qdd; /* (q, the position, unused: the compiler drops it) */
                DK(joint_rates)(C0[c], C1[c], C2[c], C3[c], x, v, a, vv, &q, &q1, &q2, &qd, &qdd);
                const real q3 = 6 * C3[c];
                real qj = q1 * j;
                real h = 3 * q2;
                h = h * v;
                h = h * a;
                qj = qj + h;
                h = q3 * vvv;
                qj = qj + h;
                top_v[c] = DK(nan_max)(top_v[c], fabs(qd));
                top_a[c] = DK(nan_max)(top_a[c], fabs(qdd));
                top_j[c] = DK(nan_max)(top_j[c], fabs(qj));
            }
        } else {
#pragma omp simd
            for (int64_t c = 0; c < n; c++) {
                real q, q1, q2, qd, qdd;
                DK(joint_rates)(C0[c], C1[c], C2[c], C3[c], x, v, a, vv, &q, &q1, &q2, &qd, &qdd);
                top_v[c] = DK(nan_max)(top_v[c], fabs(qd));
                top_a[c] = DK(nan_max)(top_a[c], fabs(qdd));
            }
        }
    }
    for (int64_t l = 0; l < nlim; l++) {
        real best = -(real)INFINITY;
        for (int64_t c = 0; c < n; c++) best = DK(nan_max)(best, top[l * n + c] / lim[l][c]);
        peak[l] = best;
    }
}

/* B paths (in: t, pt, grid, sd, Sk, u, tau, k, ps, c0, c1, c2, c3, lim_0, ..., lim_{nlim-1}; module layout
 * above, each path's rows contiguous), top (B, nlim, n) work, peak (B, nlim) out; paths shared between
 * threads. */
static int64_t DK(topp_peaks)(const real *const *in, real *top, real *peak, int64_t B, int64_t T, int64_t M, int64_t N,
                              int64_t n, int64_t nlim, int64_t nthreads) {
#pragma omp parallel for num_threads(nthreads) schedule(dynamic, 1)
    for (int64_t b = 0; b < B; b++) {
        const real *lim[3] = {in[13] + b * n, in[14] + b * n, nlim > 2 ? in[15] + b * n : NULL};
        const int64_t E = b * (N - 1) * n;
        DK(peaks_path)(in[0] + b * T, T, in[1] + b * M, in[2] + b * M, in[3] + b * M, in[5] + b * (M - 1),
                       in[4] + b * M, M, in[6][b], in[7][b], in[8] + b * N, in[9] + E, in[10] + E, in[11] + E,
                       in[12] + E, N, n, lim, nlim, top + b * nlim * n, peak + b * nlim);
    }
    return 0;
}

/* TimedPath._joint's q, q̇, q̈ (TimedPath._sample) at the times t (R, T): sample (r, m) on path rows[r T + m]
 * (rows NULL: path r), in: t, then the arrays of topp_peaks in[1..12] and end (B, n) in[13]; q, qd, qdd
 * (R, T, n) out. Rows of samples are shared between threads. */
static int64_t DK(topp_sample)(const real *const *in, const int64_t *rows, real *q, real *qd, real *qdd, int64_t R,
                               int64_t T, int64_t M, int64_t N, int64_t n, int64_t nthreads) {
#pragma omp parallel for num_threads(nthreads) schedule(dynamic, 1)
    for (int64_t r = 0; r < R; r++) {
        int64_t b = -1, h1 = 0, h2 = 0, hs = 0;
        int pt_sorted = 0, ps_sorted = 0;
        const real *pt = NULL, *grid = NULL, *sd = NULL, *Sk = NULL, *u = NULL, *ps = NULL;
        for (int64_t m = 0; m < T; m++) {
            const int64_t o = r * T + m, bb = rows ? rows[o] : r;
            if (bb != b) {  /* another path: its arrays, and the searches start afresh */
                b = bb;
                pt = in[1] + b * M, grid = in[2] + b * M, sd = in[3] + b * M, Sk = in[4] + b * M;
                u = in[5] + b * (M - 1), ps = in[8] + b * N;
                pt_sorted = DK(sorted)(pt + 1, M - 2), ps_sorted = DK(sorted)(ps + 1, N - 2);
                h1 = h2 = hs = 0;
            }
            real law[4];
            DK(law_at)(pt, grid, sd, u, Sk, M, in[6][b], in[7][b], pt_sorted, &h1, &h2, in[0][o], law);
            const real s = law[0], v = law[1], a = law[2];
            const int64_t g = DK(upper_bound_near)(ps + 1, N - 2, s, ps_sorted, &hs);
            const real x = s - ps[g];
            const real vv = v * v;
            const int last = s >= ps[N - 1];
            const int64_t e = (b * (N - 1) + g) * n;
            for (int64_t j = 0; j < n; j++) {
                real p, d1, d2;
                DK(joint_rates)(in[9][e + j], in[10][e + j], in[11][e + j], in[12][e + j], x, v, a, vv, &p, &d1,
                                &d2, qd + o * n + j, qdd + o * n + j);
                q[o * n + j] = last ? in[13][b * n + j] : p;
            }
        }
    }
    return 0;
}
