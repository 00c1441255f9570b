/* The frame terms of the whole-clip retargeting problem (diffkin/retarget/whole_clip.py, _Terms.evaluate;
 * included by _native.c once per real type, like _native_banded.c): for every frame n of N = B T frames, from
 * its end-link poses Tf (E x 4 x 4) and geometric Jacobians J (E x 6 x nv) (dk_fk's outputs), the rows
 *
 *     keypoint        w_k (p_k - x_k),                 w_k J_v
 *     orientation     w_o e_O (3.85),                  -w_o L J_w (3.87),  L = -1/2 sum_i S(d_i) S(e_i)
 *     contact height  w_c (z_lowest - r - ground),     w_c J_z(lowest point)         (foot in contact)
 *     penetration     w_p (z_p - r_p - ground),        w_p J_z(p)                    (every point below)
 *     flat foot       w_f (R e_z)_xy,                  w_f (-S(R e_z) J_w)_xy         (foot in contact)
 *
 * (a sole point's Jacobian J_v + w x off, (3.112)) enter cost_n = 1/2 |r|^2, D_n = J^T J and g_n = J^T r;
 * then the skating rows of consecutive contact frames of one clip, w_s (c_n - c_{n-1})_xy on the sole centres
 * c, add to cost_n, g_n, D_n (the diagonal part, each frame's centre Jacobian weighted by the root of its two
 * pairs' summed squared weights) and give E_n = -sum w_s^2 Jc_n^T Jc_{n-1} (the first sub-diagonal block).
 * The rows of one end link only touch the columns its Jacobian has non-zeros in (the floating base and its
 * ancestors): they are packed on those columns, their Gram matrix formed there and scattered into D_n.
 * Frames are shared between threads (pass 1), then the skating pass reads the neighbours' centres. Given
 * the chain's FK arguments (c->fk) instead of Tf and J, pass 1 evaluates the FK itself, a block of W frames
 * at a time, and reads each block's poses and Jacobians while they are in cache. */

/* Columns (of nv) where some of the 6 rows of J (6 x nv) is non-zero; returns their count. A column's flag is
 * one expression over its six entries (vectorised over the columns, each flag written once), then the flags
 * are compressed in place without a branch (cols doubles as the flag array: entry c is read before index
 * s <= c is written; a mispredicted branch per column cost more than the tests). */
static int64_t DK(support)(const real *J, int64_t nv, int64_t *cols) {
    const real *J0 = J, *J1 = J + nv, *J2 = J1 + nv, *J3 = J2 + nv, *J4 = J3 + nv, *J5 = J4 + nv;
#pragma omp simd
    for (int64_t c = 0; c < nv; c++)
        cols[c] = (J0[c] != 0) | (J1[c] != 0) | (J2[c] != 0) | (J3[c] != 0) | (J4[c] != 0) | (J5[c] != 0);
    int64_t s = 0;
    for (int64_t c = 0; c < nv; c++) { /* branch-free: a flag's column is written, kept when the flag is 1 */
        const int64_t f = cols[c];
        cols[s] = c;
        s += f;
    }
    return s;
}

/* The m rows R (m x nv) and residuals r of one end link into the frame's D (upper triangle), g and cost, on
 * the s columns cols: the rows packed on them (P, m x s), their Gram matrix G = P^T P (s x s, rank-one
 * updates of contiguous rows) scattered into D[cols, cols]. */
static void DK(clip_gram)(const real *R, const real *r, int64_t m, const int64_t *cols, int64_t s, int64_t nv,
                          real *P, real *G, real *D, real *g, real *cost) {
    for (int64_t i = 0; i < m; i++) {
        for (int64_t a = 0; a < s; a++) P[i * s + a] = R[i * nv + cols[a]];
        *cost += (real)0.5 * r[i] * r[i];
        for (int64_t a = 0; a < s; a++) g[cols[a]] += P[i * s + a] * r[i];
    }
    memset(G, 0, (size_t)(s * s) * sizeof(real));
    for (int64_t i = 0; i < m; i++) {
        const real *p = P + i * s;
        for (int64_t a = 0; a < s; a++) {
            const real pa = p[a];
            real *Ga = G + a * s;
#pragma omp simd
            for (int64_t b = 0; b < s; b++) Ga[b] += pa * p[b];
        }
    }
    for (int64_t a = 0; a < s; a++) {
        real *Da = D + cols[a] * nv;
        for (int64_t b = a; b < s; b++) Da[cols[b]] += G[a * s + b];
    }
}

/* Frame n's rows from its end-link poses Tn (E x 4 x 4) and Jacobians Jn (E x 6 x nv). */
static void DK(clip_frame)(const dk_clip *c, int64_t n, const real *Tn, const real *Jn, real *rows, real *res,
                           real *packed, real *gram, int64_t *cols, const int64_t *sup) {
    const int64_t nv = c->nv, E = c->ends, nn = nv * nv;
    const real *x = (const real *)c->x + n * c->K * 3, *Rd = (const real *)c->Rd + n * c->Ko * 9;
    const real *kw = (const real *)c->kp_w, *ow = (const real *)c->ko_w;
    const real *pts = (const real *)c->pts, *rad = (const real *)c->rad;
    const uint8_t *con = c->contact + n * 2;
    real *D = (real *)c->D + n * nn, *g = (real *)c->g + n * nv, *ctr = (real *)c->centre + n * 4;
    real *Jc = (real *)c->centre_jac + n * 4 * nv;
    real cost = 0;
    memset(D, 0, nn * sizeof(real));
    memset(g, 0, nv * sizeof(real));
    for (int64_t e = 0; e < E; e++) {
        const real *T = Tn + e * 16, *Je = Jn + e * 6 * nv, *Jw = Je + 3 * nv;
        int64_t m = 0;
        for (int64_t k = 0; k < c->K; k++) { /* keypoints */
            if (c->kp[k] != e) continue;
            for (int a = 0; a < 3; a++, m++) {
                res[m] = kw[k] * (T[4 * a + 3] - x[3 * k + a]);
                for (int64_t v = 0; v < nv; v++) rows[m * nv + v] = kw[k] * Je[a * nv + v];
            }
        }
        for (int64_t o = 0; o < c->Ko; o++) { /* orientations: e_O (3.85), -L J_w (3.87) */
            if (c->ko[o] != e) continue;
            const real *d = Rd + 9 * o; /* row-major: column i of R_d is d[3 j + i] */
            real eo[3] = {0, 0, 0}, L[9] = {0}, dot = 0;
            for (int i = 0; i < 3; i++) {
                const real di[3] = {d[i], d[3 + i], d[6 + i]}, ei[3] = {T[i], T[4 + i], T[8 + i]};
                eo[0] += ei[1] * di[2] - ei[2] * di[1];
                eo[1] += ei[2] * di[0] - ei[0] * di[2];
                eo[2] += ei[0] * di[1] - ei[1] * di[0];
                for (int a = 0; a < 3; a++) /* S(d) S(e) = e d^T - (d . e) I */
                    for (int b = 0; b < 3; b++) L[3 * a + b] += ei[a] * di[b];
                dot += di[0] * ei[0] + di[1] * ei[1] + di[2] * ei[2];
            }
            for (int a = 0; a < 3; a++) L[4 * a] -= dot;
            for (int a = 0; a < 3; a++, m++) {
                res[m] = ow[o] * (real)0.5 * eo[a];
                /* -w_o L J_w with L = -1/2 (sum S(d)S(e)): +w_o / 2 (sum S(d)S(e)) J_w */
                const real f = ow[o] * (real)0.5;
                for (int64_t v = 0; v < nv; v++)
                    rows[m * nv + v] = f * (L[3 * a] * Jw[v] + L[3 * a + 1] * Jw[nv + v] + L[3 * a + 2] * Jw[2 * nv + v]);
            }
        }
        for (int k = 0; k < 2; k++) { /* the soles */
            if (c->feet[k] != e) continue;
            const int64_t P = k ? c->P1 : c->P0, first = k ? c->P0 : 0;
            const real *pk = pts + 3 * first, *rk = rad + first;
            int64_t low = 0;
            real hlow = 0, mean[3] = {0, 0, 0};
            for (int64_t p = 0; p < P; p++) { /* the lowest point (the first of equals, as argmin) */
                real off[3];
                for (int a = 0; a < 3; a++) {
                    off[a] = T[4 * a] * pk[3 * p] + T[4 * a + 1] * pk[3 * p + 1] + T[4 * a + 2] * pk[3 * p + 2];
                    mean[a] += off[a];
                }
                const real h = off[2] + T[11] - rk[p] - (real)c->ground;
                if (p == 0 || h < hlow) low = p, hlow = h;
                if (h < 0 && c->w_pen != 0) { /* penetration */
                    res[m] = (real)c->w_pen * h;
                    for (int64_t v = 0; v < nv; v++)
                        rows[m * nv + v] = (real)c->w_pen * (Je[2 * nv + v] + Jw[v] * off[1] - Jw[nv + v] * off[0]);
                    m++;
                }
            }
            for (int a = 0; a < 3; a++) mean[a] /= (real)P;
            if (con[k]) {
                real off[3];
                for (int a = 0; a < 3; a++)
                    off[a] = T[4 * a] * pk[3 * low] + T[4 * a + 1] * pk[3 * low + 1] + T[4 * a + 2] * pk[3 * low + 2];
                const real wc = (real)c->w_contact, wf = (real)c->w_flat;
                res[m] = wc * hlow;
                for (int64_t v = 0; v < nv; v++)
                    rows[m * nv + v] = wc * (Je[2 * nv + v] + Jw[v] * off[1] - Jw[nv + v] * off[0]);
                m++;
                const real nx = T[2], ny = T[6], nz = T[10]; /* R e_z */
                res[m] = wf * nx;
                for (int64_t v = 0; v < nv; v++) rows[m * nv + v] = wf * (nz * Jw[nv + v] - ny * Jw[2 * nv + v]);
                m++;
                res[m] = wf * ny;
                for (int64_t v = 0; v < nv; v++) rows[m * nv + v] = wf * (nx * Jw[2 * nv + v] - nz * Jw[v]);
                m++;
            }
            /* the sole centre (x, y) and its Jacobian rows: J_v + w x (mean offset) */
            ctr[2 * k] = mean[0] + T[3];
            ctr[2 * k + 1] = mean[1] + T[7];
            real *jx = Jc + (2 * k) * nv, *jy = jx + nv;
            for (int64_t v = 0; v < nv; v++) {
                jx[v] = Je[v] + Jw[nv + v] * mean[2] - Jw[2 * nv + v] * mean[1];
                jy[v] = Je[nv + v] + Jw[2 * nv + v] * mean[0] - Jw[v] * mean[2];
            }
        }
        if (m) {
            if (sup) { /* the end link's structural columns (ends x (nv + 1): the count, then the columns) */
                const int64_t *se = sup + e * (nv + 1);
                DK(clip_gram)(rows, res, m, se + 1, se[0], nv, packed, gram, D, g, &cost);
            } else {
                const int64_t s = DK(support)(Je, nv, cols);
                DK(clip_gram)(rows, res, m, cols, s, nv, packed, gram, D, g, &cost);
            }
        }
    }
    ((real *)c->cost)[n] = cost;
}

/* The skating rows of frame n (t = n mod T): its pair with n - 1 and with n + 1, then D_n mirrored. */
static void DK(clip_skate)(const dk_clip *c, int64_t n, int64_t *cols, const int64_t *sup) {
    const int64_t nv = c->nv, nn = nv * nv, t = n % c->T;
    const uint8_t *con = c->contact;
    const real *ctr = (const real *)c->centre, *Jc = (const real *)c->centre_jac;
    real *D = (real *)c->D + n * nn, *En = (real *)c->E + n * nn, *g = (real *)c->g + n * nv;
    real cost = 0;
    memset(En, 0, nn * sizeof(real));
    for (int k = 0; k < 2; k++) {
        const real w = (real)c->w_skate;
        const real prev = (t >= 1 && con[2 * n + k] && con[2 * (n - 1) + k]) ? w : 0;
        const real next = (t + 1 < c->T && con[2 * n + k] && con[2 * (n + 1) + k]) ? w : 0;
        const real *J0 = Jc + (n * 4 + 2 * k) * nv; /* rows x, y of frame n's centre */
        real rp[2] = {0, 0}, rn[2] = {0, 0};
        for (int a = 0; a < 2; a++) {
            if (prev != 0) rp[a] = prev * (ctr[4 * n + 2 * k + a] - ctr[4 * (n - 1) + 2 * k + a]);
            if (next != 0) rn[a] = next * (ctr[4 * (n + 1) + 2 * k + a] - ctr[4 * n + 2 * k + a]);
            cost += (real)0.5 * rp[a] * rp[a];
            for (int64_t v = 0; v < nv; v++) g[v] += J0[a * nv + v] * (prev * rp[a] - next * rn[a]);
        }
        const real wd = prev * prev + next * next;
        if (wd == 0) continue;
        int64_t s = 0; /* the columns where a centre row of frame n or n - 1 is non-zero (or can be: the
                          foot's structural columns) */
        const real *J1 = prev != 0 ? Jc + ((n - 1) * 4 + 2 * k) * nv : J0;
        if (sup) {
            const int64_t *se = sup + c->feet[k] * (nv + 1);
            s = se[0];
            for (int64_t i = 0; i < s; i++) cols[i] = se[1 + i];
        } else {
            for (int64_t v = 0; v < nv; v++)
                if (J0[v] != 0 || J0[nv + v] != 0 || J1[v] != 0 || J1[nv + v] != 0) cols[s++] = v;
        }
        for (int a = 0; a < 2; a++)
            for (int64_t i = 0; i < s; i++) {
                const real f = wd * J0[a * nv + cols[i]];
                real *Di = D + cols[i] * nv;
                for (int64_t j = i; j < s; j++) Di[cols[j]] += f * J0[a * nv + cols[j]];
            }
        if (prev != 0) /* E_n = -w^2 Jc_n^T Jc_{n-1} */
            for (int a = 0; a < 2; a++)
                for (int64_t i = 0; i < s; i++) {
                    const real f = prev * prev * J0[a * nv + cols[i]];
                    real *Ei = En + cols[i] * nv;
                    for (int64_t j = 0; j < s; j++) Ei[cols[j]] -= f * J1[a * nv + cols[j]];
                }
    }
    ((real *)c->cost)[n] += cost;
    for (int64_t i = 0; i < nv; i++)
        for (int64_t j = 0; j < i; j++) D[i * nv + j] = D[j * nv + i];
}

/* Work space per thread: rows and residuals of one end link (rows_max x nv, rows_max), packed rows
 * (rows_max x nv), their Gram matrix (nv x nv), the support columns (nv); with c->fk (no Tf, J given), then
 * the FK's scratch and the poses and Jacobians of one block of W frames (W x ends x 16, W x ends x 6 x nv):
 * each block's FK is read while in cache instead of written out for all N frames and read back. */
static int64_t DK(clip_rows)(const dk_clip *c) {
    const int64_t nv = c->nv, N = c->N, E = c->ends;
    const int64_t rows_max = 3 * (c->K + c->Ko) + c->P0 + c->P1 + 6;
    const int fused = c->Tf == NULL || c->J == NULL;
    if (fused && (c->fk->real_bytes != (int64_t)sizeof(real) || c->fk->K != E || c->fk->nv != nv))
        return DK_ABI_ERROR; /* (dk_clip_rows checked c->fk's layout) */
    Shape shape;
    DK(Params) pp;
    if (fused) {
        read_shape(c->fk, &shape);
        if (DK(read_params)(c->fk, &shape, &pp)) return -1;
    }
    /* whole 64-byte lines of reals: the FK scratch and the int64 column scratch after them start aligned;
       each thread's block starts on its own page (as DK(team_alloc)'s) */
    const size_t reals = ((size_t)(2 * rows_max * nv + rows_max + nv * nv) + 15) & ~(size_t)15;
    const size_t fk_reals = fused ? (DK(scratch_size)(&shape) / sizeof(real) + (size_t)(W * E * (16 + 6 * nv)))
                                  : 0;
    const size_t per = ((reals + fk_reals) * sizeof(real) + (size_t)nv * sizeof(int64_t) + 4095) & ~(size_t)4095;
    int64_t nth = c->nthreads < 1 ? 1 : c->nthreads;
    if (nth > N) nth = N > 0 ? N : 1;
    const size_t sup_bytes = c->support ? (size_t)(E * (nv + 1)) * sizeof(int64_t) : 0;
    int owned;
    char *work = work_space(per * (size_t)nth + sup_bytes, &owned);
    if (!work) {
        if (fused) free(pp.fix);
        return -1;
    }
    /* the structural columns of each end link, once per call (a frame's support where none is given) */
    int64_t *sup = c->support ? (int64_t *)(work + per * (size_t)nth) : NULL;
    for (int64_t e = 0; sup && e < E; e++) {
        int64_t *se = sup + e * (nv + 1), s = 0;
        for (int64_t v = 0; v < nv; v++)
            if (c->support[e * nv + v]) se[1 + s++] = v;
        se[0] = s;
    }
    if (fused) {
        const int64_t blocks = (N + W - 1) / W;
#pragma omp parallel num_threads(nth) if (nth > 1)
        {
            real *rows = (real *)(work + per * (size_t)thread_id()), *packed = rows + rows_max * nv;
            real *res = packed + rows_max * nv, *gram = res + rows_max, *scratch = rows + reals;
            real *Tb = scratch + DK(scratch_size)(&shape) / sizeof(real), *Jb = Tb + W * E * 16;
            int64_t *cols = (int64_t *)(rows + reals + fk_reals);
            DK(Scratch) sc;
            DK(scratch_init)(&shape, &pp, scratch, &sc);
#pragma omp for schedule(static)
            for (int64_t blk = 0; blk < blocks; blk++) {
                const int64_t b0 = blk * W;
                const int nl = (int)(N - b0 < W ? N - b0 : W);
                DK(load_q)(&shape, &sc, (const real *)c->fk->q, b0, nl);
                DK(block)(&shape, &pp, &sc, 1);
                DK(fk_store)(&shape, &sc, nl, Tb, Jb);
                for (int l = 0; l < nl; l++)
                    DK(clip_frame)(c, b0 + l, Tb + l * E * 16, Jb + l * E * 6 * nv, rows, res, packed, gram, cols,
                                   sup);
            }
        }
        free(pp.fix);
    } else {
#pragma omp parallel for num_threads(nth) schedule(static) if (nth > 1)
        for (int64_t n = 0; n < N; n++) {
            real *rows = (real *)(work + per * (size_t)thread_id()), *packed = rows + rows_max * nv;
            real *res = packed + rows_max * nv, *gram = res + rows_max;
            DK(clip_frame)(c, n, (const real *)c->Tf + n * E * 16, (const real *)c->J + n * E * 6 * nv, rows, res,
                           packed, gram, (int64_t *)(rows + reals), sup);
        }
    }
#pragma omp parallel for num_threads(nth) schedule(static) if (nth > 1)
    for (int64_t n = 0; n < N; n++)
        DK(clip_skate)(c, n, (int64_t *)((real *)(work + per * (size_t)thread_id()) + reals + fk_reals), sup);
    if (owned) free(work);
    return 0;
}

/* u = the quaternion at q's columns col (4) normalised as stable_normalize does: scaled by its largest |entry|
 * first; a norm at or below DK_QSMALL gives the identity. */
static void DK(unit_read)(const real *q, const int64_t *col, real *u) {
    real m = 0, nn = 0;
    for (int c = 0; c < 4; c++) {
        u[c] = q[col[c]];
        m = fabs(u[c]) > m ? fabs(u[c]) : m;
    }
    if (!(m > 0 && m < (real)INFINITY)) m = 1;
    for (int c = 0; c < 4; c++) nn += (u[c] / m) * (u[c] / m);
    const real n = sqrt(nn) * m;
    for (int c = 0; c < 4; c++) u[c] = n <= (real)DK_QSMALL ? (real)(c == 0) : u[c] / n;
}


/* v = q1 ⊖ q0 (nv) of two configurations (nq) (ConfigurationSpace.difference, equal to rounding): the ns
 * scalars q1 - q0 (q columns sq, v columns sv), the nb quaternions (q columns bq, 4 each; v columns bv, 3
 * each) the rotation vector of a0^-1 (x) a1 along the shortest arc, each quaternion first normalised (scaled
 * by its largest |entry|; a norm at or below DK_QSMALL gives the identity, as stable_normalize). */
static void DK(difference)(const real *q0, const real *q1, const int64_t *sq, const int64_t *sv, int64_t ns,
                           const int64_t *bq, const int64_t *bv, int64_t nb, real *v) {
    for (int64_t j = 0; j < ns; j++) v[sv[j]] = q1[sq[j]] - q0[sq[j]];
    for (int64_t k = 0; k < nb; k++) {
        real a[2][4];
        DK(unit_read)(q0, bq + 4 * k, a[0]);
        DK(unit_read)(q1, bq + 4 * k, a[1]);
        const real *p = a[0], *q = a[1]; /* conj(p) (x) q: w = p0 q0 + pv.qv, v = p0 qv - q0 pv - pv x qv */
        real d[4] = {p[0] * q[0] + p[1] * q[1] + p[2] * q[2] + p[3] * q[3],
                     p[0] * q[1] - q[0] * p[1] - (p[2] * q[3] - p[3] * q[2]),
                     p[0] * q[2] - q[0] * p[2] - (p[3] * q[1] - p[1] * q[3]),
                     p[0] * q[3] - q[0] * p[3] - (p[1] * q[2] - p[2] * q[1])};
        if (d[0] < 0)
            for (int c = 0; c < 4; c++) d[c] = -d[c];
        /* 2 atan2(n, w) / n, n = |v| (rigid._atan_ratio: its Taylor branch where n^2 <= sqrt(eps) w^2) */
        const real n2 = d[1] * d[1] + d[2] * d[2] + d[3] * d[3], tiny = (real)DK_QSMALL * 1000;
        real f;
        if (n2 <= tiny * d[0] * d[0]) {
            const real x2 = n2 / (d[0] * d[0]);
            f = 2 / d[0] * (1 - x2 / 3 + x2 * x2 / 5);
        } else {
            f = 2 * atan2(sqrt(n2), d[0]) / sqrt(n2);
        }
        for (int c = 0; c < 3; c++) v[bv[3 * k + c]] = d[1 + c] * f;
    }
}

/* The joint terms of the whole-clip problem (whole_clip.py, _Terms._joint_terms: the same rows, equal to
 * rounding) of one clip of T frames q (T x nq) with the posture reference qr (T x nq), added to its cost, D, E
 * (T x nv x nv) and g (T x nv): on the ns scalar columns (q columns sq, v columns sv) the limit hinges
 * w_l ((q - hi)^+ - (lo - q)^+) and, with vstep (q̇_max / fps, NULL: none), the velocity-limit hinges
 * w_v (|Δq| - vstep)^+ sign(Δq); on all nv columns the posture w_p (q ⊖ q_ref), velocity w (q_{t+1} ⊖ q_t)
 * and acceleration w ((q_{t+1} ⊖ q_t) − (q_t ⊖ q_{t−1})) rows (DK(difference)), whose Jacobians are ±
 * multiples of I at their frames. work: T nv reals. */
static void DK(clip_joint_one)(const real *q, const real *qr, const int64_t *sq, const int64_t *sv, int64_t ns,
                               const int64_t *bq, const int64_t *bv, int64_t nb, const real *lo, const real *hi,
                               const real *vstep, int64_t T, int64_t nq, int64_t nv, const real *w, real *cost,
                               real *D, real *E, real *g, real *work) {
    const real wl = w[0], wvl = w[1], wp = w[2], wv = w[3] * w[3], wa = w[4] * w[4];
    const int64_t nn = nv * nv;
    real c = 0;
    for (int64_t t = 0; t < T; t++) {
        real *Dt = D + t * nn, *gt = g + t * nv, *dp = work + t * nv;
        const real *qt = q + t * nq;
        for (int64_t j = 0; j < ns; j++) { /* joint limits */
            const real x = qt[sq[j]];
            const real over = x > hi[j] ? x - hi[j] : 0, under = lo[j] > x ? lo[j] - x : 0;
            const real r = wl * (over - under);
            c += (real)0.5 * r * r;
            if (over > 0 || under > 0) Dt[sv[j] * (nv + 1)] += wl * wl;
            gt[sv[j]] += wl * r;
        }
        if (vstep && t >= 1) { /* velocity limits: ±(I, −I) at (t, t − 1) where beyond */
            const real *qp = q + (t - 1) * nq;
            real *Dp = D + (t - 1) * nn, *Et = E + t * nn, *gp = g + (t - 1) * nv;
            for (int64_t j = 0; j < ns; j++) {
                const real dq = qt[sq[j]] - qp[sq[j]], ex = fabs(dq) - vstep[j];
                if (!(ex > 0)) continue;
                const real r = wvl * ex * (dq > 0 ? 1 : (dq < 0 ? -1 : 0));
                const int64_t k = sv[j] * (nv + 1);
                c += (real)0.5 * r * r;
                Dt[k] += wvl * wvl;
                Dp[k] += wvl * wvl;
                Et[k] -= wvl * wvl;
                gt[sv[j]] += wvl * r;
                gp[sv[j]] -= wvl * r;
            }
        }
        DK(difference)(qr + t * nq, qt, sq, sv, ns, bq, bv, nb, dp); /* posture: q ⊖ q_ref */
        for (int64_t v = 0; v < nv; v++) { /* posture, then the differences' diagonal and off-diagonal parts */
            const real rp = wp * dp[v];
            c += (real)0.5 * rp * rp;
            real dd = wp * wp;
            gt[v] += wp * wp * dp[v];
            if (T > 1) dd += wv * ((t >= 1) + (t + 1 < T));
            if (T > 2) dd += wa * ((t >= 2) + 4 * (t >= 1 && t + 1 < T) + (t + 2 < T));
            Dt[v * (nv + 1)] += dd;
        }
        if (t >= 1) { /* E_t's diagonal: −w_v², and −2 w_a² per acceleration row through (t, t − 1) */
            real e = -wv;
            if (T > 2) e -= 2 * wa * ((t + 1 < T) + (t >= 2));
            real *Et = E + t * nn;
            for (int64_t v = 0; v < nv; v++) Et[v * (nv + 1)] += e;
        }
    }
    if (T > 1) { /* velocity rows d_i = q_{i+1} ⊖ q_i (into work): g_{i+1} += w² d_i, g_i −= w² d_i */
        real *d = work;
        for (int64_t i = 0; i + 1 < T; i++) DK(difference)(q + i * nq, q + (i + 1) * nq, sq, sv, ns, bq, bv, nb,
                                                          d + i * nv);
        for (int64_t i = 0; i + 1 < T; i++)
            for (int64_t v = 0; v < nv; v++) {
                const real x = d[i * nv + v];
                c += (real)0.5 * wv * x * x;
                g[(i + 1) * nv + v] += wv * x;
                g[i * nv + v] -= wv * x;
            }
        for (int64_t i = 0; i + 2 < T; i++) /* acceleration rows a_i = d_{i+1} − d_i at frames (i, i+1, i+2) */
            for (int64_t v = 0; v < nv; v++) {
                const real a = d[(i + 1) * nv + v] - d[i * nv + v];
                c += (real)0.5 * wa * a * a;
                g[i * nv + v] += wa * a;
                g[(i + 1) * nv + v] -= 2 * wa * a;
                g[(i + 2) * nv + v] += wa * a;
            }
    }
    *cost += c;
}

/* B clips: q, qr (B x T x nq), cost (B), D, E (B x T x nv x nv), g (B x T x nv); idx = (sq, sv, bq, bv); the
 * weights w = (limit, velocity_limit, posture, velocity, acceleration). Clips are shared between threads.
 * Returns 0, or -1 when the work space cannot be allocated. */
static int64_t DK(clip_joint)(const real *q, const real *qr, const int64_t *const *idx, int64_t ns, int64_t nb,
                              const real *lo, const real *hi, const real *vstep, int64_t B, int64_t T, int64_t nq,
                              int64_t nv, const real *w, real *cost, real *D, real *E, real *g, int64_t nthreads) {
    if (nthreads < 1) nthreads = 1;
    if (nthreads > B) nthreads = B > 0 ? B : 1;
    real *work = malloc((size_t)(T * nv) * (size_t)nthreads * sizeof(real));
    if (!work) return -1;
#pragma omp parallel for num_threads(nthreads) schedule(static) if (nthreads > 1)
    for (int64_t b = 0; b < B; b++)
        DK(clip_joint_one)(q + b * T * nq, qr + b * T * nq, idx[0], idx[1], ns, idx[2], idx[3], nb, lo, hi, vstep,
                           T, nq, nv, w, cost + b, D + b * T * nv * nv, E + b * T * nv * nv, g + b * T * nv,
                           work + (size_t)(T * nv) * (size_t)thread_id());
    free(work);
    return 0;
}

/* The whole-clip step of B clips of T frames (whole_clip.py: _Terms.project(space.integrate(q, step)), equal
 * to rounding): out = q ⊕ step (scalars q + v; quaternions normalise(Q) (x) exp(w / 2), exp(w / 2) =
 * (cos(th / 2), sin(th / 2) w / th), th = |w|, as ConfigurationSpace.integrate), clamped to the limits qlo,
 * qhi (nq; torch.minimum then torch.maximum, as chain.clamp_to_limits), then, with vstep (ns; NULL: none),
 * frame after frame the scalar coordinates onto [out_{t-1} - vstep, out_{t-1} + vstep] ∩ [lo, hi] (lo, hi:
 * the limits of the ns scalars). Clips are shared between threads. */
static int64_t DK(clip_step)(const real *q, const real *step, const int64_t *const *idx, int64_t ns, int64_t nb,
                             const real *qlo, const real *qhi, const real *lo, const real *hi, const real *vstep,
                             int64_t B, int64_t T, int64_t nq, int64_t nv, real *out, int64_t nthreads) {
    const int64_t *sq = idx[0], *sv = idx[1], *bq = idx[2], *bv = idx[3];
    if (nthreads < 1) nthreads = 1;
    if (nthreads > B) nthreads = B > 0 ? B : 1;
#pragma omp parallel for num_threads(nthreads) schedule(static) if (nthreads > 1)
    for (int64_t b = 0; b < B; b++)
        for (int64_t t = 0; t < T; t++) {
            const int64_t n = b * T + t;
            const real *qn = q + n * nq, *v = step + n * nv;
            real *o = out + n * nq;
            for (int64_t j = 0; j < ns; j++) o[sq[j]] = qn[sq[j]] + v[sv[j]];
            for (int64_t k = 0; k < nb; k++) {
                real u[4];
                DK(unit_read)(qn, bq + 4 * k, u);
                const real wx = v[bv[3 * k]], wy = v[bv[3 * k + 1]], wz = v[bv[3 * k + 2]];
                const real h = (real)0.5 * sqrt(wx * wx + wy * wy + wz * wz);
                /* sinc(h) with its Taylor branch below eps^(1/4), as _numerics.sinc */
                const real sc = h < sqrt((real)DK_QSMALL * 1000) ? 1 - h * h / 6 + h * h * h * h / 120 : sin(h) / h;
                const real e0 = cos(h), ev[3] = {(real)0.5 * sc * wx, (real)0.5 * sc * wy, (real)0.5 * sc * wz};
                const int64_t *c = bq + 4 * k;
                o[c[0]] = u[0] * e0 - (u[1] * ev[0] + u[2] * ev[1] + u[3] * ev[2]);
                o[c[1]] = u[0] * ev[0] + e0 * u[1] + (u[2] * ev[2] - u[3] * ev[1]);
                o[c[2]] = u[0] * ev[1] + e0 * u[2] + (u[3] * ev[0] - u[1] * ev[2]);
                o[c[3]] = u[0] * ev[2] + e0 * u[3] + (u[1] * ev[1] - u[2] * ev[0]);
            }
            for (int64_t i = 0; i < nq; i++) o[i] = DK(nan_max)(DK(nan_min)(o[i], qhi[i]), qlo[i]);
            if (vstep && t >= 1) {
                const real *before = o - nq;
                for (int64_t j = 0; j < ns; j++) {
                    const real l = DK(nan_max)(before[sq[j]] - vstep[j], lo[j]);
                    const real u = DK(nan_min)(before[sq[j]] + vstep[j], hi[j]);
                    o[sq[j]] = DK(nan_min)(DK(nan_max)(o[sq[j]], l), u);
                }
            }
        }
    return 0;
}
