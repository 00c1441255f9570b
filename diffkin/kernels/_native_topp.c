/* The backward and forward passes of TOPP-RA (diffkin/trajectories/time_optimal.py, _topp) for CPU tensors
 * without autograd (included by _native.c once per real type, like _native_banded.c). Every constraint row
 * but the moving one is reduced before the passes (in torch); the passes meet, per grid interval i of a path,
 *
 *     backward: kn_i = min(K_{i+1}, xq_i),  K_i = min(fixed_i, max(0, min_r (Aq_ir kn_i + G_ir) / C_ir))
 *     forward:  x_i = min(x_i, K_i),  u = max(min(min_r (Gu_ir - Bu_ir x_i) / Au_ir, (kn_i - x_i) / d_i),
 *               -x_i / d_i),  x_{i+1} = min(max(x_i + d_i u, 0), K_{i+1})
 *
 * with K_{M-1} = 0 and x_0 = 0: one grid point after another, a few flops each, which torch spends one
 * operator call on (most of the time of a short batch). The same operations in the same order as the torch
 * loop, each a statement of its own and never contracted into a fused multiply-add, and the minima and maxima
 * propagate NaN as torch.minimum / amin / clamp do: the same floats. Paths are shared between threads. */

#if defined(__clang__)
#pragma clang fp contract(off)
#elif defined(__GNUC__)
#pragma GCC push_options
#pragma GCC optimize("fp-contract=off")
#endif

static inline real DK(nan_min)(real a, real b) { return (a < b || a != a) ? a : b; }
static inline real DK(nan_max)(real a, real b) { return (a > b || a != a) ? a : b; }

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

static int64_t DK(topp_passes)(const real *Aq, const real *G, const real *C, const real *Au, const real *Bu,
                               const real *Gu, const real *fixed, const real *xq, const real *d, real *K,
                               real *Kn, real *x, int64_t B, int64_t M, int64_t R, int64_t Ru, int64_t nthreads) {
#pragma omp parallel for num_threads(nthreads) schedule(dynamic, 1)
    for (int64_t b = 0; b < B; b++) {
        const int64_t I = b * (M - 1);
        DK(topp_path)(Aq + I * R, G + I * R, C + I * R, Au + I * Ru, Bu + I * Ru, Gu + I * Ru, fixed + I, xq + I,
                      d + I, M, R, Ru, K + b * M, Kn + I, x + b * M);
    }
    return 0;
}

#if defined(__clang__)
#pragma clang fp contract(on)
#elif defined(__GNUC__)
#pragma GCC pop_options
#endif
