/* The block-banded SPD solve of diffkin/kernels/banded.py (block_banded_solve) for CPU tensors without
 * autograd (included by _native.c once per real type, like _native_solve.c). H x = g with H given by its
 * lower blocks D_t = H_{t,t}, E_t = H_{t,t-1}, F_t = H_{t,t-2} (n x n, row-major; E_0, F_0, F_1 unused);
 * the block Cholesky factor has the same band (banded.py's module doc):
 *
 *     B_t = F_t L_{t-2}^{-T},  A_t = (E_t - B_t A_{t-1}^T) L_{t-1}^{-T},  L_t = chol(D_t - B_t B_t^T - A_t A_t^T)
 *
 * then y_t = L_t^{-1}(g_t - A_t y_{t-1} - B_t y_{t-2}) and x_t = L_t^{-T}(y_t - A_{t+1}^T x_{t+1} -
 * B_{t+2}^T x_{t+2}). The factors are kept transposed (U_t = L_t^T, A_t^T, B_t^T, row-major) so that every
 * O(n^3) step is S -= P^T Q over rows (DK(tile)); their rows are padded to ld, a multiple of the vector
 * width (zeros beyond column n), so that every row is whole aligned vectors: no remainder columns. The
 * factors of one system live in a work space of 3 T n ld reals. A block that is not positive definite
 * gives a NaN pivot (sqrt of a negative), which reaches x, as the torch path's cholesky_ex does. Systems
 * (the leading batch) are shared between threads. */

#ifndef DK_BANDED_ONCE
#define DK_BANDED_ONCE
/* One vector: a register of the target (the compiler splits a wider one, and a tile that then needs more
 * registers than there are spills: 4 x 5 AVX-512 vectors, 4 x 3 elsewhere, fit with room for the operands). */
#if defined(__AVX512F__)
#define DK_VBYTES 64
#define DK_NV 5 /* vectors of a register tile's row: n = 35 doubles in one tile row (ld 40) */
#elif defined(__AVX__)
#define DK_VBYTES 32
#define DK_NV 3
#else
#define DK_VBYTES 16
#define DK_NV 3
#endif
#define DK_MR 4 /* rows of a register tile */
#endif

typedef real DK(vec) __attribute__((vector_size(DK_VBYTES)));
#define DK_V ((int64_t)(DK_VBYTES / sizeof(real)))

/* The register tile of every O(n^3) step: rows i0 .. i0 + mr of C, columns c0 .. c0 + nv V (whole
 * vectors), C_ij -= sum_{k0 <= k < k1} P_ki Q_kj (P, Q, C: rows ld apart). `qlow`: Q is lower triangular
 * (Q_kj = 0 for j > k), so row k of Q adds to the vectors that start at or before column k only. With
 * Ud (the upper factor U, rinv its reciprocal diagonal), the tile's rows are then solved among
 * themselves, X <- U_II^{-T} X (the diagonal block of a lower solve, its earlier rows already
 * subtracted). mr, nv, qlow are constants where inlined (DK(tile_at)), so acc stays in registers: each Q
 * vector loaded is used mr times, each P scalar nv times. */
static inline __attribute__((always_inline)) void DK(tile)(real *restrict C, const real *restrict P,
                                                           const real *restrict Q, int64_t ld, int64_t i0,
                                                           int64_t c0, int64_t k0, int64_t k1,
                                                           const real *restrict Ud, const real *restrict rinv,
                                                           const int mr, const int nv, const int qlow) {
    typedef DK(vec) vec;
    vec acc[DK_MR][DK_NV];
    for (int r = 0; r < mr; r++)
        for (int v = 0; v < nv; v++) acc[r][v] = *(const vec *)(C + (i0 + r) * ld + c0 + v * DK_V);
    for (int s = qlow ? 0 : nv - 1; s < nv; s++) { /* k's for which vectors 0 .. s hold non-zeros of Q */
        int64_t ks = qlow ? c0 + s * DK_V : k0, ke = qlow && s + 1 < nv ? c0 + (s + 1) * DK_V : k1;
        if (ks < k0) ks = k0;
        if (ke > k1) ke = k1;
        for (int64_t k = ks; k < ke; k++) {
            const real *q = Q + k * ld + c0, *p = P + k * ld + i0;
            for (int v = 0; v <= s; v++) {
                const vec qv = *(const vec *)(q + v * DK_V);
                for (int r = 0; r < mr; r++) acc[r][v] -= p[r] * qv;
            }
        }
    }
    if (Ud)
        for (int r = 0; r < mr; r++) {
            const real d = rinv[i0 + r];
            for (int v = 0; v < nv; v++) acc[r][v] *= d;
            for (int s = r + 1; s < mr; s++) {
                const real u = Ud[(i0 + r) * ld + i0 + s];
                for (int v = 0; v < nv; v++) acc[s][v] -= u * acc[r][v];
            }
        }
    for (int r = 0; r < mr; r++)
        for (int v = 0; v < nv; v++) *(vec *)(C + (i0 + r) * ld + c0 + v * DK_V) = acc[r][v];
}

#define DK_TILE_CASE(m, v)                                                                                 \
    case (m) * 8 + (v):                                                                                    \
        if (qlow) DK(tile)(C, P, Q, ld, i0, c0, k0, k1, Ud, rinv, m, v, 1);                                \
        else DK(tile)(C, P, Q, ld, i0, c0, k0, k1, Ud, rinv, m, v, 0);                                     \
        break;
#if DK_NV == 5
#define DK_TILE_ROW(m) DK_TILE_CASE(m, 1) DK_TILE_CASE(m, 2) DK_TILE_CASE(m, 3) DK_TILE_CASE(m, 4) DK_TILE_CASE(m, 5)
#else
#define DK_TILE_ROW(m) DK_TILE_CASE(m, 1) DK_TILE_CASE(m, 2) DK_TILE_CASE(m, 3)
#endif

/* DK(tile) for mr <= DK_MR rows and nv <= DK_NV vectors, each size compiled on its own. C may be rows of
 * Q (a lower solve's, the Cholesky's: the tile's rows are not among those it reads). */
static void DK(tile_at)(real *C, const real *P, const real *Q, int64_t ld, int64_t i0, int mr, int64_t c0,
                        int nv, int64_t k0, int64_t k1, int qlow, const real *Ud, const real *rinv) {
    switch (mr * 8 + nv) {
        DK_TILE_ROW(1) DK_TILE_ROW(2) DK_TILE_ROW(3) DK_TILE_ROW(4)
    }
}
#undef DK_TILE_CASE
#undef DK_TILE_ROW

/* X <- L^{-1} X = U^{-T} X for upper-triangular U (n rows of X, ld apart), left-looking by tiles of rows:
 * each tile takes every earlier row at once (X_I -= U_{<I, I}^T X_{<I}), then is solved in registers.
 * `lower`: X is lower triangular, and so is the result (the tile stops after its last row's column). */
static void DK(lower_solve)(const real *restrict U, const real *restrict rinv, real *restrict X, int64_t n,
                            int64_t ld, int lower) {
    for (int64_t i0 = 0; i0 < n; i0 += DK_MR) {
        const int mr = n - i0 < DK_MR ? (int)(n - i0) : DK_MR;
        const int64_t cend = lower ? i0 + mr : n;
        for (int64_t c0 = 0; c0 < cend; c0 += DK_NV * DK_V) {
            const int64_t left = (cend - c0 + DK_V - 1) / DK_V;
            DK(tile_at)(X, U, X, ld, i0, mr, c0, left < DK_NV ? (int)left : DK_NV, 0, i0, lower, U, rinv);
        }
    }
}

/* S -= P^T Q for P, Q (n rows, ld apart); skips only products with zeros or unread results: `upper`
 * updates the tiles that hold the upper triangle j >= i (the Cholesky step reads no other), `plow` /
 * `qlow` say P / Q are lower triangular (P_ki = 0 for i > k, Q_kj = 0 for j > k). */
static void DK(sub_tn)(real *restrict S, const real *restrict P, const real *restrict Q, int64_t n, int64_t ld,
                       int upper, int plow, int qlow) {
    for (int64_t i0 = 0; i0 < n; i0 += DK_MR) {
        const int mr = n - i0 < DK_MR ? (int)(n - i0) : DK_MR;
        for (int64_t c0 = upper ? i0 / DK_V * DK_V : 0; c0 < n; c0 += DK_NV * DK_V) {
            const int64_t left = (n - c0 + DK_V - 1) / DK_V;
            DK(tile_at)(S, P, Q, ld, i0, mr, c0, left < DK_NV ? (int)left : DK_NV, plow ? i0 : 0, n, qlow, NULL,
                        NULL);
        }
    }
}

/* The upper Cholesky factor U (S = U^T U) in place of the symmetric S (upper triangle read; below the
 * diagonal is left as it is, never read), rinv its reciprocal diagonal; left-looking by tiles of rows:
 * each tile takes every finished row at once, then its rows are factored among themselves (whole vectors
 * from the one that holds the diagonal: the entries left of it are not read). */
static void DK(cholesky_upper)(real *restrict S, real *restrict rinv, int64_t n, int64_t ld) {
    typedef DK(vec) vec;
    for (int64_t i0 = 0; i0 < n; i0 += DK_MR) {
        const int mr = n - i0 < DK_MR ? (int)(n - i0) : DK_MR;
        const int64_t cs = i0 / DK_V * DK_V;
        if (i0 > 0)
            for (int64_t c0 = cs; c0 < n; c0 += DK_NV * DK_V) {
                const int64_t left = (n - c0 + DK_V - 1) / DK_V;
                DK(tile_at)(S, S, S, ld, i0, mr, c0, left < DK_NV ? (int)left : DK_NV, 0, i0, 0, NULL, NULL);
            }
        for (int64_t j = i0; j < i0 + mr; j++) {
            real *sj = S + j * ld;
            const real d = sqrt(sj[j]); /* NaN for a block that is not positive definite */
            const real inv = 1 / d;
            rinv[j] = inv;
            for (int64_t c = cs; c < ld; c += DK_V) *(vec *)(sj + c) *= inv;
            sj[j] = d;
            for (int64_t i = j + 1; i < i0 + mr; i++) {
                const real a = sj[i];
                real *si = S + i * ld;
                for (int64_t c = cs; c < ld; c += DK_V) *(vec *)(si + c) -= a * *(const vec *)(sj + c);
            }
        }
    }
}

/* dst = src^T (n x n; src row-major, dst rows ld apart, zeros beyond column n), src read in its order (a
 * stream the hardware prefetches; the blocks come from the caller's large arrays, not in cache), dst
 * written across (in L1). */
static void DK(transpose_into)(real *restrict dst, const real *restrict src, int64_t n, int64_t ld) {
    int64_t nt = 0; /* the leading nt x nt in register tiles (DK_TRANSPOSE: a scalar loop cost 0.4 ms of a
                       4.5 ms solve, its stores a row apart), the rest entry by entry */
#if defined(__AVX2__)
    nt = n / DK_TILE * DK_TILE;
    for (int64_t i = 0; i < nt; i += DK_TILE)
        for (int64_t j = 0; j < nt; j += DK_TILE) DK_TRANSPOSE(src + i * n + j, (size_t)n, dst + j * ld + i, ld);
#endif
    for (int64_t i = 0; i < n; i++)
        for (int64_t j = i < nt ? nt : 0; j < n; j++) dst[j * ld + i] = src[i * n + j];
    for (int64_t j = 0; j < n; j++)
        for (int64_t i = n; i < ld; i++) dst[j * ld + i] = 0;
}

/* 1 when X (n x n, row-major) is zero above its diagonal (rows ld apart). */
static int DK(is_lower)(const real *X, int64_t n, int64_t ld) {
    for (int64_t i = 0; i < n; i++)
        for (int64_t j = i + 1; j < n; j++)
            if (X[i * ld + j] != 0) return 0;
    return 1;
}

/* 1 when X (n x n, row-major) is diagonal: no non-zero (nor NaN) off its diagonal. Each row's non-zeros
 * are counted without a branch per entry (a compare and branch per entry showed as a tenth of the solve's
 * samples on the whole-clip problem's diagonal F). */
static int DK(is_diagonal)(const real *restrict X, int64_t n) {
    for (int64_t i = 0; i < n; i++) {
        const real *xi = X + i * n;
        int64_t nz = 0;
#pragma omp simd reduction(+ : nz)
        for (int64_t j = 0; j < n; j++) nz += xi[j] != 0;
        if (nz > (xi[i] != 0)) return 0;
    }
    return 1;
}

/* diag[t] = 1 where F_t (t >= 2) is diagonal (e.g. an acceleration term's): then B_t^T is its diagonal
 * solved, lower triangular, and is built without reading F_t's other entries. */
static void DK(diagonal_flags)(const real *F, int64_t T, int64_t n, unsigned char *diag) {
    for (int64_t t = 0; t < T; t++) diag[t] = t >= 2 && DK(is_diagonal)(F + t * n * n, n);
}

/* The forward substitution's step t with the factors of frames t - 2 .. t (banded_one's work space, run as
 * soon as frame t is factored, while its blocks are in cache): y_t = L_t^{-1}(g_t - A_t y_{t-1} - B_t y_{t-2})
 * into x (module doc). r (ld reals) holds the vector being formed, padded with zeros beyond n so that every
 * product with a factor's row runs over whole vectors. */
static void DK(forward_step)(const real *restrict U, const real *restrict At, const real *restrict Bt,
                             const real *restrict rinv, const real *restrict g, real *restrict x, int64_t t,
                             int64_t n, int64_t ld, real *restrict r) {
    const int64_t nl = n * ld;
    real *y = x + t * n;
    const real *Ut = U + t * nl, *ri = rinv + t * ld;
    memcpy(r, g + t * n, n * sizeof(real));
    for (int64_t i = n; i < ld; i++) r[i] = 0;
    for (int64_t s = 1; s <= 2 && s <= t; s++) { /* r -= M_t y_{t-s}: rows of M_t^T, whole vectors */
        const real *M = (s == 1 ? At : Bt) + t * nl, *ys = x + (t - s) * n;
        for (int64_t k = 0; k < n; k++) {
            const real c = ys[k], *mk = M + k * ld;
#pragma omp simd aligned(r, mk : DK_VBYTES)
            for (int64_t i = 0; i < ld; i++) r[i] -= c * mk[i];
        }
    }
    for (int64_t j = 0; j < n; j++) {
        const real c = r[j] * ri[j], *uj = Ut + j * ld;
        y[j] = c;
#pragma omp simd
        for (int64_t i = j + 1; i < n; i++) r[i] -= c * uj[i];
    }
}

/* The back substitution x = L^{-T} y (y in x, from DK(forward_step)); r (2 ld reals) as there. */
static void DK(back_substitute)(const real *restrict U, const real *restrict At, const real *restrict Bt,
                                const real *restrict rinv, real *restrict x, int64_t T, int64_t n, int64_t ld,
                                real *restrict r) {
    const int64_t nl = n * ld;
    real *xs = r + ld;
    for (int64_t i = n; i < ld; i++) xs[i] = 0;
    for (int64_t t = T - 1; t >= 0; t--) { /* back: x_t = U_t^{-1}(y_t - A_{t+1}^T x_{t+1} - B_{t+2}^T x_{t+2}) */
        real *xt = x + t * n;
        const real *Ut = U + t * nl, *ri = rinv + t * ld;
        memcpy(r, xt, n * sizeof(real));
        for (int64_t s = 1; s <= 2 && t + s < T; s++) {
            const real *M = (s == 1 ? At : Bt) + (t + s) * nl;
            memcpy(xs, x + (t + s) * n, n * sizeof(real)); /* zeros beyond n: whole-vector products */
            for (int64_t i = 0; i < n; i++) {
                const real *mi = M + i * ld;
                real acc = 0;
#pragma omp simd reduction(+ : acc) aligned(xs, mi : DK_VBYTES)
                for (int64_t k = 0; k < ld; k++) acc += mi[k] * xs[k];
                r[i] -= acc;
            }
        }
        for (int64_t i = n - 1; i >= 0; i--) {
            const real *ui = Ut + i * ld;
            real acc = 0;
#pragma omp simd reduction(+ : acc)
            for (int64_t k = i + 1; k < n; k++) acc += ui[k] * r[k];
            r[i] = (r[i] - acc) * ri[i];
        }
        memcpy(xt, r, n * sizeof(real));
    }
}

/* One system: work holds 3 T n ld reals of factors, T ld reciprocal diagonals and 2 ld of vectors. */
static void DK(banded_one)(const real *D, const real *E, const real *F, const unsigned char *fdiag,
                           const real *g, real *x, int64_t T, int64_t n, real shift, real *work) {
    const int64_t ld = (n + DK_V - 1) / DK_V * DK_V, nl = n * ld, nn = n * n;
    real *U = work, *At = work + T * nl, *Bt = work + 2 * T * nl; /* U_t = L_t^T, A_t^T, B_t^T */
    real *rinv = work + 3 * T * nl;                                 /* 1 / diag(U_t) */
    for (int64_t t = 0; t < T; t++) {
        real *Ut = U + t * nl, *a = At + t * nl, *b = Bt + t * nl;
        for (int64_t i = 0; i < n; i++) {
            memcpy(Ut + i * ld, D + t * nn + i * n, n * sizeof(real));
            for (int64_t j = n; j < ld; j++) Ut[i * ld + j] = 0;
            Ut[i * ld + i] += shift; /* D_t + shift I (the caller's damping) */
        }
        int low = 0; /* F_t^T lower triangular (e.g. the diagonal of an acceleration term): so is B_t^T */
        if (t >= 2) {
            const real *Ft = F + t * nn;
            if (fdiag[t]) {
                memset(b, 0, (size_t)nl * sizeof(real));
                for (int64_t i = 0; i < n; i++) b[i * ld + i] = Ft[i * n + i];
                low = 1;
            } else {
                DK(transpose_into)(b, Ft, n, ld);
                low = DK(is_lower)(b, n, ld);
            }
            DK(lower_solve)(U + (t - 2) * nl, rinv + (t - 2) * ld, b, n, ld, low); /* B_t^T = L_{t-2}^{-1} F_t^T */
            DK(sub_tn)(Ut, b, b, n, ld, 1, low, low); /* - B_t B_t^T (upper triangle) */
        }
        if (t >= 1) {
            DK(transpose_into)(a, E + t * nn, n, ld);
            if (t >= 2) DK(sub_tn)(a, At + (t - 1) * nl, b, n, ld, 0, 0, low); /* E_t^T - A_{t-1} B_t^T */
            DK(lower_solve)(U + (t - 1) * nl, rinv + (t - 1) * ld, a, n, ld, 0);
            DK(sub_tn)(Ut, a, a, n, ld, 1, 0, 0); /* - A_t A_t^T (upper triangle) */
        }
        DK(cholesky_upper)(Ut, rinv + t * ld, n, ld);
        DK(forward_step)(U, At, Bt, rinv, g, x, t, n, ld, rinv + T * ld);
    }
    DK(back_substitute)(U, At, Bt, rinv, x, T, n, ld, rinv + T * ld);
}

/* batch systems of T blocks of n: D, E (batch x T x n x n), F (batch x T x n x n, or T x n x n shared by
 * every system where f_shared: read once into cache, not batch times from memory, and tested for a
 * diagonal once), g and x (batch x T x n), contiguous; shift (batch) or NULL: each system's D_t taken as
 * D_t + shift I (an LM damping without a copy of D). Returns 0, or -1 when the work space cannot be
 * allocated. */
static int64_t DK(banded_solve)(const real *D, const real *E, const real *F, int64_t f_shared, const real *g,
                                const real *shift, real *x, int64_t batch, int64_t T, int64_t n,
                                int64_t nthreads) {
    const int64_t ld = (n + DK_V - 1) / DK_V * DK_V;
    const size_t reals = (size_t)((3 * n + 1) * T * ld + 2 * ld); /* one system's work (DK(banded_one)) */
    const size_t per = reals + ((size_t)T + sizeof(real) - 1) / sizeof(real); /* + its F_t diagonal flags */
    const size_t stride = (per + DK_V - 1) / DK_V * DK_V; /* each thread's work aligned */
    const size_t sys = (size_t)(T * n * n), vec = (size_t)(T * n), fsys = f_shared ? 0 : sys;
    if (batch < 1) return 0; /* nothing to solve (and no work space to take) */
    if (nthreads < 1) nthreads = 1;
    if (nthreads > batch) nthreads = batch;
    int owned;
    real *work = work_space(stride * (size_t)nthreads * sizeof(real), &owned); /* whole aligned vectors */
    if (!work) return -1;
    unsigned char *shared_flags = (unsigned char *)(work + reals); /* thread 0's, filled once when shared */
    if (f_shared) DK(diagonal_flags)(F, T, n, shared_flags);
#pragma omp parallel for num_threads(nthreads) schedule(dynamic, 1) if (nthreads > 1)
    for (int64_t b = 0; b < batch; b++) {
        real *w = work + stride * (size_t)(nthreads > 1 ? thread_id() : 0);
        unsigned char *flags = f_shared ? shared_flags : (unsigned char *)(w + reals);
        if (!f_shared) DK(diagonal_flags)(F + b * fsys, T, n, flags);
        DK(banded_one)(D + b * sys, E + b * sys, F + b * fsys, flags, g + b * vec, x + b * vec, T, n,
                       shift ? shift[b] : 0, w);
    }
    if (owned) free(work);
    return 0;
}
#undef DK_V
