/* The continuous check of a plan's spline (diffkin/motion/_spline.py, _spline_clear) for CPU tensors without
 * autograd (included by _native.c once per real type, like _native_topp.c): the positions of the clamped
 * cubic spline at the fine samples u, their bound-length chords and the check points at the marks, each
 * sample one pass through its own segment (torch spends (B, fine, nq) temporaries and a gather per binary
 * search step). The same operations in the same order as the torch code (poly_eval position_only, the
 * chord's joints summed first to last, cumsum in order; _native.c includes this file with fused
 * multiply-adds off): the same floats. Paths are shared between threads. */

/* _Path.eval(s, position_only=True) of one path: its knots ps (N), coefficients c0..c3 (N - 1, n) and end
 * point (n); g the segment (torch.searchsorted of the inner knots, right); q (n) out. */
static inline void DK(spline_at)(const real *ps, const real *c0, const real *c1, const real *c2, const real *c3,
                                 const real *end, int64_t N, int64_t n, real s, int64_t g, real *q) {
    const real x = s - ps[g];
    const int last = s >= ps[N - 1];
    for (int64_t j = 0; j < n; j++) {
        const int64_t e = g * n + j;
        real p = c3[e] * x;
        p = p + c2[e];
        p = p * x;
        p = p + c1[e];
        p = p * x;
        p = p + c0[e];
        q[j] = last ? end[j] : p;
    }
}

/* Per path b: inside[b] (1 where every fine sample lies within [lo, hi], else 0) and cum (F + 1): the running
 * bound-length Σ_j reach_j |Δq_j| over the fine samples u (F + 1), cum[0] = 0. q2 (2 n per path) work. */
static void DK(spline_fine)(const real *u, int64_t F, const real *ps, const real *c0, const real *c1,
                            const real *c2, const real *c3, const real *end, const real *lo, const real *hi,
                            const real *reach, int64_t B, int64_t N, int64_t n, real *cum, real *inside,
                            real *work, int64_t nthreads) {
#pragma omp parallel for num_threads(nthreads) schedule(dynamic, 1)
    for (int64_t b = 0; b < B; b++) {
        const int64_t E = b * (N - 1) * n;
        const real *kb = ps + b * N;
        real *q = work + b * 2 * n, *prev = q + n, *cb = cum + b * (F + 1);
        const int sorted = DK(sorted)(kb + 1, N - 2);
        int64_t h = 0;
        int in = 1;
        for (int64_t f = 0; f <= F; f++) {
            const int64_t g = DK(upper_bound_near)(kb + 1, N - 2, u[f], sorted, &h);
            DK(spline_at)(kb, c0 + E, c1 + E, c2 + E, c3 + E, end + b * n, N, n, u[f], g, q);
            for (int64_t j = 0; j < n; j++) in &= (q[j] >= lo[j]) & (q[j] <= hi[j]);
            if (f == 0) {
                cb[0] = 0;
            } else {
                real chord = 0;
                for (int64_t j = 0; j < n; j++) {
                    real d = q[j] - prev[j];
                    d = fabs(d) * reach[j];
                    chord = j ? chord + d : d;
                }
                cb[f] = cb[f - 1] + chord;
            }
            real *t = prev;
            prev = q, q = t;
        }
        inside[b] = in;
    }
}

/* torch.searchsorted(a[:L], x, right=False): the count of a's sorted values < x (torch's lower bound). */
static inline int64_t DK(lower_bound)(const real *a, int64_t L, real x) {
    int64_t lo = 0, hi = L;
    while (lo < hi) {
        const int64_t mid = lo + ((hi - lo) >> 1);
        if (!(a[mid] >= x)) lo = mid + 1;
        else hi = mid;
    }
    return lo;
}

/* The check points of path b: its marks m · step[b] (m = 0..count[b]) placed on cum (B, F + 1) (the first
 * fine sample whose running length reaches the mark, at most F) and the spline evaluated there, into q
 * (Σ (count + 1), n) from row first[b]. */
static void DK(spline_marks)(const real *u, int64_t F, const real *cum, const real *step, const int64_t *count,
                             const int64_t *first, const real *ps, const real *c0, const real *c1, const real *c2,
                             const real *c3, const real *end, int64_t B, int64_t N, int64_t n, real *q,
                             int64_t nthreads) {
#pragma omp parallel for num_threads(nthreads) schedule(dynamic, 1)
    for (int64_t b = 0; b < B; b++) {
        const int64_t E = b * (N - 1) * n;
        const real *kb = ps + b * N, *cb = cum + b * (F + 1);
        const int sorted = DK(sorted)(kb + 1, N - 2);
        int64_t h = 0;
        for (int64_t m = 0; m <= count[b]; m++) {
            const real mark = (real)m * step[b];
            int64_t i = DK(lower_bound)(cb, F + 1, mark);
            i = i > F ? F : i;
            const int64_t g = DK(upper_bound_near)(kb + 1, N - 2, u[i], sorted, &h);
            DK(spline_at)(kb, c0 + E, c1 + E, c2 + E, c3 + E, end + b * n, N, n, u[i], g, q + (first[b] + m) * n);
        }
    }
}
