/* The chain product (2.50) and the geometric Jacobian (3.30) fused into one pass per configuration: the
 * native twin of diffkin.kernels.tree / diffkin.kernels.jacobian for CPU batches without autograd.
 *
 * It computes exactly what column_frames + the Jacobian kernel compute, from the same constants (the chain's
 * fixed transforms as Python-float plans, here dense 3x4 rows with the plan's snapped zeros skipped):
 *
 *     F_j = F_parent(j) . Pre_j . M(m_j q[i_j] + b_j) . Post_j,   end k:  F_ends[k] . E_k
 *     J_k[:, i_j] += m_j [z_j x (p_e - p_j); z_j]  (revolute)  or  m_j [z_j; 0]  (prismatic)
 *
 * with z_j, p_j the z axis and origin of F_parent . Pre_j . M_j. Configurations are processed in blocks of W
 * lanes; every loop over the lanes is branch-free so the compiler vectorises it, and sin/cos are evaluated by
 * a vectorisable Cody-Waite reduction and Cephes polynomials (|x| >= 1e5 falls back to libm per lane).
 * Blocks are shared between threads with a dynamic schedule, so a thread on a busy core simply takes fewer
 * blocks. The float kernel evaluates sin/cos in double and everything else in float.
 *
 * Model layout (built by diffkin/kernels/native.py):
 *   ints:  J, K, n, then parent[J], revolute[J], qidx[J], has_pre[J], has_post[J], has_base, end_joint[K],
 *          has_end[K], ancestor[K*J]
 *   reals: mult[J], qoff[J], pre[12J], post[12J], base[12], end[12K]   (3x4 row-major blocks)
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define W 16
#define SERIAL_MAX 512 /* configurations below which no thread is started */

typedef struct {
    int J, K, n, has_base;
    const int32_t *parent, *revolute, *qidx, *has_pre, *has_post, *end_joint, *has_end, *anc;
} Shape;

static void read_shape(const int32_t *ip, Shape *s) {
    s->J = ip[0];
    s->K = ip[1];
    s->n = ip[2];
    const int32_t *p = ip + 3;
    s->parent = p;   p += s->J;
    s->revolute = p; p += s->J;
    s->qidx = p;     p += s->J;
    s->has_pre = p;  p += s->J;
    s->has_post = p; p += s->J;
    s->has_base = *p++;
    s->end_joint = p; p += s->K;
    s->has_end = p;   p += s->K;
    s->anc = p;
}

/* sin and cos of W lanes of double, vectorisable. */
static void sincos_lanes(const double *x, double *s, double *c) {
    const double two_over_pi = 0.63661977236758134308;
    const double P1 = 1.57079632673412561417e+00, P2 = 6.07710050630396597660e-11,
                 P3 = 2.02226624871116645580e-21;
    int big = 0;
    for (int l = 0; l < W; l++) big |= !(fabs(x[l]) < 1e5);
    if (big) { /* far from the origin (or not finite): libm's full reduction */
        for (int l = 0; l < W; l++) { s[l] = sin(x[l]); c[l] = cos(x[l]); }
        return;
    }
#pragma omp simd
    for (int l = 0; l < W; l++) {
        double k = nearbyint(x[l] * two_over_pi);
        double r = ((x[l] - k * P1) - k * P2) - k * P3;
        double z = r * r;
        double sp = r + r * z * (-1.66666666666666307295e-1 + z * (8.33333333332211858878e-3 +
                    z * (-1.98412698295895385996e-4 + z * (2.75573136213857245213e-6 +
                    z * (-2.50507477628578072866e-8 + z * 1.58962301576546568060e-10)))));
        double cp = 1.0 - 0.5 * z + z * z * (4.16666666666665929218e-2 + z * (-1.38888888888730564116e-3 +
                    z * (2.48015872888517045348e-5 + z * (-2.75573141792967388112e-7 +
                    z * (2.08757008419747316778e-9 + z * -1.13585365213876817300e-11)))));
        long q = (long)k & 3;
        double sv = (q & 1) ? cp : sp;
        double cv = (q & 1) ? sp : cp;
        s[l] = (q & 2) ? -sv : sv;
        c[l] = ((q + 1) & 2) ? -cv : cv;
    }
}

#define DEFINE_KERNEL(real, SUFFIX)                                                                           \
                                                                                                              \
/* out = P . A for frames P (12 x W lanes) and a constant 3x4 A (zeros skipped; last row 0 0 0 1). */         \
static void mulfix_##SUFFIX(const real *P, const real *A, real *out) {                                        \
    for (int r = 0; r < 3; r++) {                                                                             \
        const real *Pr = P + 4 * r * W;                                                                       \
        real *Or = out + 4 * r * W;                                                                           \
        for (int col = 0; col < 4; col++) {                                                                   \
            real acc[W];                                                                                      \
            if (col == 3) memcpy(acc, Pr + 3 * W, sizeof acc); else memset(acc, 0, sizeof acc);               \
            for (int k = 0; k < 3; k++) {                                                                     \
                const real a = A[4 * k + col];                                                                \
                if (a == (real)0) continue;                                                                   \
                const real *Pk = Pr + k * W;                                                                  \
                _Pragma("omp simd") for (int l = 0; l < W; l++) acc[l] += Pk[l] * a;                                              \
            }                                                                                                 \
            memcpy(Or + col * W, acc, sizeof acc);                                                            \
        }                                                                                                     \
    }                                                                                                         \
}                                                                                                             \
                                                                                                              \
static void block_##SUFFIX(const Shape *s, const real *mult, const real *qoff, const real *pre,              \
                           const real *post, const real *base, const real *endT, const real *q, int64_t b0,   \
                           int nl, real *T, real *Jac, real *F, real *G, real *axes, real *Jb,                \
                           int64_t *bad) {                                                                    \
    const int J = s->J, K = s->K, n = s->n;                                                                   \
    real qv[64 * W];                                                                                          \
    real *qlanes = n <= 64 ? qv : (real *)malloc(sizeof(real) * (size_t)n * W);                               \
    int64_t nonfinite = 0;                                                                                    \
    for (int l = 0; l < W; l++) {                                                                             \
        const real *qr = q + (b0 + (l < nl ? l : nl - 1)) * n;                                                \
        for (int i = 0; i < n; i++) {                                                                         \
            qlanes[i * W + l] = qr[i];                                                                        \
            if (l < nl && !isfinite(qr[i])) nonfinite++;                                                      \
        }                                                                                                     \
    }                                                                                                         \
    *bad += nonfinite;                                                                                        \
    real basef[12 * W];                                                                                       \
    for (int e = 0; e < 12; e++)                                                                              \
        _Pragma("omp simd") for (int l = 0; l < W; l++)                                                                           \
            basef[e * W + l] = s->has_base ? base[e] : (real)((e % 5) == 0); /* identity: 0, 5, 10 */         \
    for (int j = 0; j < J; j++) {                                                                             \
        const real *P = s->parent[j] < 0 ? basef : F + (size_t)s->parent[j] * 12 * W;                         \
        if (s->has_pre[j]) mulfix_##SUFFIX(P, pre + 12 * j, G);                                               \
        else memcpy(G, P, sizeof(real) * 12 * W);                                                             \
        const real m = mult[j], b = qoff[j];                                                                  \
        const real *qj = qlanes + (size_t)s->qidx[j] * W;                                                     \
        if (s->revolute[j]) {                                                                                 \
            double ang[W], sn[W], cs[W];                                                                      \
            _Pragma("omp simd") for (int l = 0; l < W; l++) ang[l] = (double)(qj[l] * m + b);                                     \
            sincos_lanes(ang, sn, cs);                                                                        \
            for (int r = 0; r < 3; r++) {                                                                     \
                real *restrict x = G + 4 * r * W, *restrict y = x + W;                                        \
                _Pragma("omp simd") for (int l = 0; l < W; l++) {                                                                 \
                    const real c = (real)cs[l], sv = (real)sn[l];                                             \
                    const real xn = c * x[l] + sv * y[l];                                                     \
                    y[l] = c * y[l] - sv * x[l];                                                              \
                    x[l] = xn;                                                                                \
                }                                                                                             \
            }                                                                                                 \
        } else {                                                                                              \
            for (int r = 0; r < 3; r++) {                                                                     \
                real *restrict z = G + (4 * r + 2) * W, *restrict p = G + (4 * r + 3) * W;                    \
                _Pragma("omp simd") for (int l = 0; l < W; l++) p[l] += (qj[l] * m + b) * z[l];                                   \
            }                                                                                                 \
        }                                                                                                     \
        if (Jac) /* the motion axis z and a point p on it, before Post */                                     \
            for (int r = 0; r < 3; r++) {                                                                     \
                memcpy(axes + ((size_t)j * 6 + r) * W, G + (4 * r + 2) * W, sizeof(real) * W);                \
                memcpy(axes + ((size_t)j * 6 + 3 + r) * W, G + (4 * r + 3) * W, sizeof(real) * W);            \
            }                                                                                                 \
        real *Fj = F + (size_t)j * 12 * W;                                                                    \
        if (s->has_post[j]) mulfix_##SUFFIX(G, post + 12 * j, Fj);                                            \
        else memcpy(Fj, G, sizeof(real) * 12 * W);                                                            \
    }                                                                                                         \
    for (int k = 0; k < K; k++) {                                                                             \
        const int e = s->end_joint[k];                                                                        \
        const real *P = e < 0 ? basef : F + (size_t)e * 12 * W;                                               \
        if (s->has_end[k]) { mulfix_##SUFFIX(P, endT + 12 * k, G); P = G; }                                   \
        for (int l = 0; l < nl; l++) {                                                                        \
            real *To = T + ((b0 + l) * K + k) * 16;                                                           \
            for (int r = 0; r < 12; r++) To[r] = P[r * W + l];                                                \
            To[12] = 0; To[13] = 0; To[14] = 0; To[15] = 1;                                                   \
        }                                                                                                     \
        if (!Jac) continue;                                                                                   \
        const real *restrict e0 = P + 3 * W, *restrict e1 = P + 7 * W, *restrict e2 = P + 11 * W;             \
        memset(Jb, 0, sizeof(real) * 6 * (size_t)n * W);                                                      \
        for (int j = 0; j < J; j++) {                                                                         \
            if (!s->anc[k * J + j]) continue;                                                                 \
            const real *restrict z0 = axes + (size_t)j * 6 * W, *restrict z1 = z0 + W, *restrict z2 = z1 + W; \
            const real *restrict p0 = z2 + W, *restrict p1 = p0 + W, *restrict p2 = p1 + W;                  \
            const real m = mult[j];                                                                           \
            const int i = s->qidx[j];                                                                         \
            real *restrict c0 = Jb + (size_t)(0 * n + i) * W, *restrict c1 = Jb + (size_t)(1 * n + i) * W,    \
                 *restrict c2 = Jb + (size_t)(2 * n + i) * W, *restrict c3 = Jb + (size_t)(3 * n + i) * W,    \
                 *restrict c4 = Jb + (size_t)(4 * n + i) * W, *restrict c5 = Jb + (size_t)(5 * n + i) * W;    \
            if (s->revolute[j]) {                                                                             \
                _Pragma("omp simd") for (int l = 0; l < W; l++) {                                                                 \
                    const real d0 = e0[l] - p0[l], d1 = e1[l] - p1[l], d2 = e2[l] - p2[l];                       \
                    c0[l] += m * (z1[l] * d2 - z2[l] * d1);                                                   \
                    c1[l] += m * (z2[l] * d0 - z0[l] * d2);                                                   \
                    c2[l] += m * (z0[l] * d1 - z1[l] * d0);                                                   \
                    c3[l] += m * z0[l];                                                                       \
                    c4[l] += m * z1[l];                                                                       \
                    c5[l] += m * z2[l];                                                                       \
                }                                                                                             \
            } else {                                                                                          \
                _Pragma("omp simd") for (int l = 0; l < W; l++) {                                                                 \
                    c0[l] += m * z0[l];                                                                       \
                    c1[l] += m * z1[l];                                                                       \
                    c2[l] += m * z2[l];                                                                       \
                }                                                                                             \
            }                                                                                                 \
        }                                                                                                     \
        for (int l = 0; l < nl; l++) {                                                                        \
            real *Jo = Jac + ((b0 + l) * K + k) * 6 * (int64_t)n;                                             \
            for (int r = 0; r < 6 * n; r++) Jo[r] = Jb[(size_t)r * W + l];                                    \
        }                                                                                                     \
    }                                                                                                         \
    if (qlanes != qv) free(qlanes);                                                                           \
}                                                                                                             \
                                                                                                              \
/* T (B, K, 4, 4) and, when Jac is not NULL, J (B, K, 6, n) of q (B, n); returns the number of non-finite    \
 * entries of q (their outputs are not meaningful), or -1 when memory ran out. */                             \
int64_t dk_fk_##SUFFIX(const int32_t *ip, const real *rp, const real *q, int64_t B, real *T, real *Jac,      \
                       int nthreads) {                                                                        \
    Shape s;                                                                                                  \
    read_shape(ip, &s);                                                                                       \
    const int J = s.J, n = s.n;                                                                               \
    const real *mult = rp, *qoff = rp + J, *pre = rp + 2 * J, *post = pre + 12 * J, *base = post + 12 * J,    \
               *endT = base + 12;                                                                             \
    const int64_t nblocks = (B + W - 1) / W;                                                                  \
    const size_t per = sizeof(real) * W * ((size_t)J * 12 + 12 + (Jac ? (size_t)J * 6 + 6 * (size_t)n : 0));  \
    int64_t bad = 0, failed = 0;                                                                              \
    if (nthreads < 1 || B <= SERIAL_MAX) nthreads = 1;                                                        \
    _Pragma("omp parallel num_threads(nthreads) reduction(+ : bad, failed) if (nthreads > 1)")                \
    {                                                                                                         \
        real *buf = (real *)malloc(per);                                                                      \
        if (!buf) {                                                                                           \
            failed += 1;                                                                                      \
        } else {                                                                                              \
            real *F = buf, *G = F + (size_t)J * 12 * W, *axes = G + 12 * W,                                   \
                 *Jb = axes + (Jac ? (size_t)J * 6 * W : 0);                                                  \
            _Pragma("omp for schedule(dynamic, 8)")                                                           \
            for (int64_t blk = 0; blk < nblocks; blk++) {                                                     \
                const int64_t b0 = blk * W;                                                                   \
                const int nl = (int)(B - b0 < W ? B - b0 : W);                                                \
                block_##SUFFIX(&s, mult, qoff, pre, post, base, endT, q, b0, nl, T, Jac, F, G, axes, Jb,      \
                               &bad);                                                                         \
            }                                                                                                 \
            free(buf);                                                                                        \
        }                                                                                                     \
    }                                                                                                         \
    return failed ? -1 : bad;                                                                                 \
}

DEFINE_KERNEL(double, f64)
DEFINE_KERNEL(float, f32)
