/* The block-banded SPD solve of diffkin/kernels/banded.py (block_banded_solve) for CPU tensors without
 * autograd (included by _native.c once per real type, like _native_solve.c). H x = g with H given by its
 * lower blocks D_t = H_{t,t}, E_t = H_{t,t-1}, F_t = H_{t,t-2} (n x n, row-major; E_0, F_0, F_1 unused);
 * the block Cholesky factor has the same band (banded.py's module doc):
 *
 *     B_t = F_t L_{t-2}^{-T},  A_t = (E_t - B_t A_{t-1}^T) L_{t-1}^{-T},  L_t = chol(D_t - B_t B_t^T - A_t A_t^T)
 *
 * then y_t = L_t^{-1}(g_t - A_t y_{t-1} - B_t y_{t-2}) and x_t = L_t^{-T}(y_t - A_{t+1}^T x_{t+1} -
 * B_{t+2}^T x_{t+2}). The factors are kept transposed (U_t = L_t^T, A_t^T, B_t^T, row-major) so that every
 * O(n^3) loop is an axpy of contiguous rows, which the compiler vectorises without reassociating sums;
 * the factors of one system live in a work space of 3 T n^2 reals. A block that is not positive definite
 * gives a NaN pivot (sqrt of a negative), which reaches x, as the torch path's cholesky_ex does. Systems
 * (the leading batch) are shared between threads. */

static inline void DK(axpy)(real *restrict y, real a, const real *restrict x, int64_t n) {
#pragma omp simd
    for (int64_t k = 0; k < n; k++) y[k] -= a * x[k];
}

/* X <- L^{-1} X = U^{-T} X for upper-triangular U (rows of X: n reals each); `lower`: X is lower
 * triangular, and so is the result (row j then has no entry beyond column j). Rows are eliminated four at
 * a time: each later row takes the four in one pass (one load and store of it per four products). */
static void DK(lower_solve)(const real *restrict U, real *restrict X, int64_t n, int lower) {
    int64_t j0 = 0;
    for (; j0 + 4 <= n; j0 += 4) {
        const int64_t len = lower ? j0 + 4 : n;
        for (int64_t j = j0; j < j0 + 4; j++) { /* the four rows among themselves */
            real *xj = X + j * n;
            const real d = 1 / U[j * n + j];
            for (int64_t k = 0; k < len; k++) xj[k] *= d;
            for (int64_t i = j + 1; i < j0 + 4; i++) DK(axpy)(X + i * n, U[j * n + i], xj, len);
        }
        const real *x0 = X + j0 * n, *x1 = x0 + n, *x2 = x1 + n, *x3 = x2 + n;
        for (int64_t i = j0 + 4; i < n; i++) {
            const real a0 = U[j0 * n + i], a1 = U[(j0 + 1) * n + i], a2 = U[(j0 + 2) * n + i],
                       a3 = U[(j0 + 3) * n + i];
            real *xi = X + i * n;
#pragma omp simd
            for (int64_t k = 0; k < len; k++) xi[k] -= a0 * x0[k] + a1 * x1[k] + a2 * x2[k] + a3 * x3[k];
        }
    }
    for (int64_t j = j0; j < n; j++) {
        real *xj = X + j * n;
        const real d = 1 / U[j * n + j];
        const int64_t len = lower ? j + 1 : n;
        for (int64_t k = 0; k < len; k++) xj[k] *= d;
        for (int64_t i = j + 1; i < n; i++) DK(axpy)(X + i * n, U[j * n + i], xj, len);
    }
}

/* S -= P^T Q for row-major P, Q (S_ij -= sum_k P_ki Q_kj); four rows of Q per pass over a row of S, so
 * that S is loaded and stored a quarter as often as Q is read. Structure skips only products with zeros:
 * `upper` updates the upper triangle j >= i only (the Cholesky step reads no other), `plow` / `qlow` say P /
 * Q are lower triangular (zero above the diagonal: P_ki = 0 for i > k, Q_kj = 0 for j > k). */
static void DK(sub_tn)(real *restrict S, const real *restrict P, const real *restrict Q, int64_t n, int upper,
                       int plow, int qlow) {
    int64_t k = 0;
    for (; k + 4 <= n; k += 4) {
        const real *q0 = Q + k * n, *q1 = q0 + n, *q2 = q1 + n, *q3 = q2 + n;
        const int64_t iend = plow ? k + 4 : n, jend = qlow ? k + 4 : n;
        for (int64_t i = 0; i < iend; i++) {
            const real a0 = P[k * n + i], a1 = P[(k + 1) * n + i], a2 = P[(k + 2) * n + i],
                       a3 = P[(k + 3) * n + i];
            real *si = S + i * n;
#pragma omp simd
            for (int64_t j = upper ? i : 0; j < jend; j++)
                si[j] -= a0 * q0[j] + a1 * q1[j] + a2 * q2[j] + a3 * q3[j];
        }
    }
    for (; k < n; k++) {
        const int64_t iend = plow ? k + 1 : n, jend = qlow ? k + 1 : n;
        for (int64_t i = 0; i < iend; i++) {
            const int64_t j0 = upper ? i : 0;
            if (j0 < jend) DK(axpy)(S + i * n + j0, P[k * n + i], Q + k * n + j0, jend - j0);
        }
    }
}

/* 1 when X (n x n, row-major) is zero above its diagonal. */
static int DK(is_lower)(const real *X, int64_t n) {
    for (int64_t i = 0; i < n; i++)
        for (int64_t j = i + 1; j < n; j++)
            if (X[i * n + j] != 0) return 0;
    return 1;
}

/* The upper Cholesky factor U (S = U^T U) in place of the symmetric S (lower triangle zeroed). */
static void DK(cholesky_upper)(real *restrict S, int64_t n) {
    for (int64_t j = 0; j < n; j++) {
        real *sj = S + j * n;
        const real d = sqrt(sj[j]); /* NaN for a block that is not positive definite */
        const real inv = 1 / d;
        for (int64_t k = 0; k < j; k++) sj[k] = 0;
        sj[j] = d;
        for (int64_t k = j + 1; k < n; k++) sj[k] *= inv;
        for (int64_t i = j + 1; i < n; i++) DK(axpy)(S + i * n + i, sj[i], sj + i, n - i);
    }
}

/* dst = src^T (n x n, row-major) in 8 x 8 tiles: every cache line read or written is used whole (the
 * blocks come from the caller's large arrays, mostly not in cache). */
static void DK(transpose_into)(real *restrict dst, const real *restrict src, int64_t n) {
    for (int64_t ib = 0; ib < n; ib += 8)
        for (int64_t jb = 0; jb < n; jb += 8) {
            const int64_t ie = ib + 8 < n ? ib + 8 : n, je = jb + 8 < n ? jb + 8 : n;
            for (int64_t i = ib; i < ie; i++)
                for (int64_t j = jb; j < je; j++) dst[j * n + i] = src[i * n + j];
        }
}

/* 1 when X (n x n, row-major) is diagonal; then B <- X (its diagonal, zeros elsewhere). The test counts
 * each row's non-zeros without a branch per entry (a compare and branch per entry showed as a tenth of
 * the solve's samples on the whole-clip problem's diagonal F; about 2 % of the solve's time saved). */
static int DK(copy_diagonal)(real *restrict B, const real *restrict X, int64_t n) {
    for (int64_t i = 0; i < n; i++) {
        const real *xi = X + i * n;
        int64_t nz = 0;
#pragma omp simd reduction(+ : nz)
        for (int64_t j = 0; j < n; j++) nz += xi[j] != 0;
        if (nz > (xi[i] != 0)) return 0;
    }
    memset(B, 0, (size_t)(n * n) * sizeof(real));
    for (int64_t i = 0; i < n; i++) B[i * n + i] = X[i * n + i];
    return 1;
}

static void DK(banded_one)(const real *D, const real *E, const real *F, const real *g, real *x, int64_t T,
                           int64_t n, real shift, real *work) {
    const int64_t nn = n * n;
    real *U = work, *At = work + T * nn, *Bt = work + 2 * T * nn; /* U_t = L_t^T, A_t^T, B_t^T */
    for (int64_t t = 0; t < T; t++) {
        real *Ut = U + t * nn, *a = At + t * nn, *b = Bt + t * nn;
        memcpy(Ut, D + t * nn, nn * sizeof(real));
        for (int64_t i = 0; i < n; i++) Ut[i * n + i] += shift; /* D_t + shift I (the caller's damping) */
        int low = 0; /* F_t^T lower triangular (e.g. the diagonal of an acceleration term): so is B_t^T */
        if (t >= 2) {
            low = DK(copy_diagonal)(b, F + t * nn, n);
            if (!low) {
                DK(transpose_into)(b, F + t * nn, n);
                low = DK(is_lower)(b, n);
            }
            DK(lower_solve)(U + (t - 2) * nn, b, n, low); /* B_t^T = L_{t-2}^{-1} F_t^T */
            DK(sub_tn)(Ut, b, b, n, 1, low, low);            /* - B_t B_t^T (upper triangle) */
        }
        if (t >= 1) {
            DK(transpose_into)(a, E + t * nn, n);
            if (t >= 2) DK(sub_tn)(a, At + (t - 1) * nn, b, n, 0, 0, low); /* E_t^T - A_{t-1} B_t^T */
            DK(lower_solve)(U + (t - 1) * nn, a, n, 0);
            DK(sub_tn)(Ut, a, a, n, 1, 0, 0);            /* - A_t A_t^T (upper triangle) */
        }
        DK(cholesky_upper)(Ut, n);
    }
    for (int64_t t = 0; t < T; t++) { /* forward: y_t = L_t^{-1}(g_t - A_t y_{t-1} - B_t y_{t-2}), in x */
        real *y = x + t * n;
        const real *Ut = U + t * nn;
        memcpy(y, g + t * n, n * sizeof(real));
        for (int64_t k = 0; k < n; k++) {
            if (t >= 1) DK(axpy)(y, x[(t - 1) * n + k], At + t * nn + k * n, n);
            if (t >= 2) DK(axpy)(y, x[(t - 2) * n + k], Bt + t * nn + k * n, n);
        }
        for (int64_t j = 0; j < n; j++) {
            y[j] /= Ut[j * n + j];
            DK(axpy)(y + j + 1, y[j], Ut + j * n + j + 1, n - j - 1);
        }
    }
    for (int64_t t = T - 1; t >= 0; t--) { /* back: x_t = U_t^{-1}(y_t - A_{t+1}^T x_{t+1} - B_{t+2}^T x_{t+2}) */
        real *r = x + t * n;
        const real *Ut = U + t * nn;
        for (int64_t s = 1; s <= 2 && t + s < T; s++) {
            const real *M = (s == 1 ? At : Bt) + (t + s) * nn, *xs = x + (t + s) * n;
            for (int64_t i = 0; i < n; i++) {
                real acc = 0;
#pragma omp simd reduction(+ : acc)
                for (int64_t k = 0; k < n; k++) acc += M[i * n + k] * xs[k];
                r[i] -= acc;
            }
        }
        for (int64_t i = n - 1; i >= 0; i--) {
            real acc = 0;
#pragma omp simd reduction(+ : acc)
            for (int64_t k = i + 1; k < n; k++) acc += Ut[i * n + k] * r[k];
            r[i] = (r[i] - acc) / Ut[i * n + i];
        }
    }
}

/* batch systems of T blocks of n: D, E (batch x T x n x n), F (batch x T x n x n, or T x n x n shared by
 * every system where f_shared: read once into cache, not batch times from memory), g and x (batch x T x
 * n), contiguous; shift (batch) or NULL: each system's D_t taken as D_t + shift I (an LM damping without a
 * copy of D). Returns 0, or -1 when the work space cannot be allocated. */
static int64_t DK(banded_solve)(const real *D, const real *E, const real *F, int64_t f_shared, const real *g,
                                const real *shift, real *x, int64_t batch, int64_t T, int64_t n,
                                int64_t nthreads) {
    const size_t per = (size_t)(3 * T * n * n), sys = (size_t)(T * n * n), vec = (size_t)(T * n);
    const size_t fsys = f_shared ? 0 : sys;
    if (nthreads < 1) nthreads = 1;
    if (nthreads > batch) nthreads = batch;
    real *work = malloc(per * (size_t)nthreads * sizeof(real));
    if (!work) return -1;
    if (nthreads == 1) {
        for (int64_t b = 0; b < batch; b++)
            DK(banded_one)(D + b * sys, E + b * sys, F + b * fsys, g + b * vec, x + b * vec, T, n,
                           shift ? shift[b] : 0, work);
    } else {
#pragma omp parallel for num_threads(nthreads) schedule(dynamic, 1)
        for (int64_t b = 0; b < batch; b++)
            DK(banded_one)(D + b * sys, E + b * sys, F + b * fsys, g + b * vec, x + b * vec, T, n,
                           shift ? shift[b] : 0, work + per * (size_t)thread_id());
    }
    free(work);
    return 0;
}
