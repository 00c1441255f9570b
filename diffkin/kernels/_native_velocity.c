/* One step of differential IK, mink's solve_ik, in one C call (included by _native.c once per real type,
 * like _native_solve.c): for each row, the chain's FK and Jacobians (DK(block), the fused pass), the
 * tasks' least-squares objective and the limits' box, and the exact minimiser of the box QP.
 * diffkin/ik/_native_velocity.py prepares the arrays; tests/test_native_velocity.py checks the result
 * against mink (daqp) and against the torch path.
 *
 * The QP on the step dq (nv), as mink builds it (solve_ik.py, tasks/task.py):
 *
 *     min 1/2 dq^T H dq + c^T dq   s.t.  lo <= dq <= hi,        v = dq / dt,  q_next = q (+) dq
 *     H = damping I + sum_tasks (A^T A + mu I),  c = - sum_tasks A^T b,  A = C J,  b = -gain C e,
 *     mu = lm_damping |b|^2,  C = diag(cost)
 *
 * Frame task (tasks/frame_task.py, lie/se3.py, lie/so3.py): T_b the end link's pose, T_t the target (both
 * in the chain's base frame); e = log(T_b^-1 T_t) (the body twist [v; w], SE(3)'s log through the unit
 * quaternion of the rotation, as mink's SE3 objects hold it: Shepperd's mju_mat2Quat, then the log of
 * mink's lie/_lie_ops_c.c with its switches at 1e-10); J = -jlog(T_t^-1 T_b) J_body = -ljacinv(e) J_body,
 * ljacinv of (179b) with Q of (180) (Sola et al.), the 6 x 6 identity where |w|^2 < 1e-10 (mink's switch);
 * J_body = [R_b^T J_v; R_b^T J_w] from the geometric Jacobian (3.30).
 * Posture task (tasks/posture_task.py): e = q (-) q_ref (MuJoCo's mj_differentiatePos: scalars q - q_ref,
 * a quaternion log(Q_ref^-1 Q) as mju_subQuat), J = I; the caller gives the free joints' columns cost 0
 * (mink zeroes them).
 * ConfigurationLimit (limits/configuration_limit.py): gain (lo_i - q_i) <= dq_i <= gain (hi_i - q_i) on
 * limited scalar velocities (the caller folds min_distance_from_limits into lo, hi).
 * VelocityLimit (limits/velocity_limit.py): |dq_i| <= dt vmax_i.
 * Where the two leave no room (q beyond a position limit by more than the velocity limit lets it return
 * in one step) the box is the point of the velocity range nearest the position range: the row moves back
 * at the velocity limit (ok[row] = 0: mink's QP is infeasible there).
 *
 * The box QP is solved exactly by active sets on the Cholesky factors of H's free block (vel_box_qp): the
 * unconstrained minimiser first (one factorisation when no bound is active, the common case of a
 * teleoperation loop), then primal-dual active-set rounds that change every wrong bound at once (2-3 more
 * factorisations where bounds are active), with a primal active-set method as the finite fallback.
 *
 * Interface: dk_vel (DK_VEL_FIELDS), its own struct with its own version (dk_layout_vel, dk_names_vel), so
 * that the FK's dk_args keeps its layout; dk_velocity(chain's dk_args, dk_vel, dk_watch or NULL) for a
 * batch, dk_velocity_one(dk_args, dk_vel, dk_watch, q, target, q_ref, v, q_next, dt) for one row (and
 * dk_velocity_step, the same with its arguments in two blocks: two for ctypes to convert). Rows run
 * in blocks of W lanes (one FK pass per block, of WN lanes where the block has at most WN rows), blocks
 * shared between nthreads threads above SERIAL_MAX rows; a serial call may keep the plans and work space in
 * `work` (dk_velocity_work_bytes bytes) between calls.
 */
#ifndef DK_VEL_TYPES
#define DK_VEL_TYPES
#define DK_VEL_VERSION 3 /* bump with every change of DK_VEL_FIELDS (and _native_velocity.py's VERSION) */
#define DK_LOG_EPS 1e-10 /* mink's get_epsilon(float64): the Taylor switches of SO3 / SE3 log and ljacinv */
#define DK_VEL_F64(name) name##_f64
#define DK_VEL_F32(name) name##_f32

#define DK_VEL_FIELDS(X) \
    X(int64_t, version, "DK_VEL_VERSION") \
    X(int64_t, size, "sizeof(dk_vel)") \
    X(int64_t, nthreads, "threads for batches of more than SERIAL_MAX rows") \
    X(int64_t, batch, "B rows") \
    X(int64_t, n_frames, "F frame tasks") \
    X(const int32_t *, frame_end, "[F] the end link (index into the chain's ends) of each frame task") \
    X(const void *, frame_cost, "[6F] reals: position (3) then orientation (3) cost of each frame task") \
    X(const void *, frame_gain, "[F] reals") \
    X(const void *, frame_lm, "[F] reals: lm_damping") \
    X(const void *, target, "[F 16] reals per row: target poses (4x4 row-major) in the base frame") \
    X(int64_t, target_stride, "reals from one row's targets to the next (0: shared by every row)") \
    X(const void *, posture_cost, "[nv] reals, NULL: no posture task") \
    X(double, posture_gain, "") \
    X(double, posture_lm, "lm_damping of the posture task") \
    X(const void *, q_ref, "[nq] reals per row") \
    X(int64_t, ref_stride, "reals from one row's q_ref to the next (0: shared)") \
    X(const void *, pos_lo, "[nv] reals: lower limit of each scalar velocity's coordinate (-inf: none); " \
                            "NULL: no configuration limit") \
    X(const void *, pos_hi, "[nv] reals: upper limits (+inf: none)") \
    X(double, limit_gain, "the configuration limit's gain") \
    X(const void *, vmax, "[nv] reals: velocity limits (+inf: none); NULL: no velocity limit") \
    X(double, dt, "seconds") \
    X(double, damping, "added to H's diagonal") \
    X(const void *, q, "[B nq] reals in") \
    X(void *, v, "[B nv] reals out: dq / dt") \
    X(void *, q_next, "[B nq] reals out, or NULL: q (+) dq") \
    X(uint8_t *, ok, "[B] out, or NULL: 1 where q was finite, the box feasible and the QP solved") \
    X(void *, work, "NULL, or dk_velocity_work_bytes bytes kept between serial calls") \
    X(int64_t, ready, "in/out: work holds the chain's plans (0: make them)") \
    X(int64_t, busy, "dk_velocity_one: a call is using work now") \
    X(int64_t, n_bodies, "v3: B bodies of the centre of mass (ComTask)") \
    X(const int32_t *, body_frame, "[B] the frame each body moves with (-1: the base)") \
    X(const void *, body_point, "[3B] reals: each body's centre of mass in its frame") \
    X(const void *, body_weight, "[B] reals: m_i / M") \
    X(const void *, com_cost, "[3] reals; NULL: no ComTask") \
    X(double, com_gain, "the ComTask's gain") \
    X(double, com_lm, "the ComTask's lm_damping") \
    X(const void *, com_target, "[3] reals per row: the centre of mass's target in the base frame") \
    X(int64_t, com_stride, "reals from one row's com_target to the next (0: shared)") \
    X(int64_t, n_caps, "G capsules of the collision rows (0: no CollisionLimit)") \
    X(const int32_t *, cap_frame, "[G] the frame each capsule moves with (-1: the base)") \
    X(const void *, cap_a, "[3G] reals: segment starts in their frames") \
    X(const void *, cap_b, "[3G] reals: segment ends in their frames") \
    X(const void *, cap_r, "[G] reals: radii") \
    X(const uint8_t *, cap_moving, "[G] 1: the capsule's world rows are checked") \
    X(int64_t, n_pairs, "P checked self pairs") \
    X(const int32_t *, pair_i, "[P] capsule indices") \
    X(const int32_t *, pair_j, "[P] capsule indices") \
    X(int64_t, n_round, "world spheres, capsules and points (segments with a radius)") \
    X(const void *, round_a, "[3 n_round] reals: segment starts in the base frame") \
    X(const void *, round_b, "[3 n_round] reals: segment ends") \
    X(const void *, round_r, "[n_round] reals: radii") \
    X(int64_t, n_half, "world half-spaces {x : n.x <= offset}") \
    X(const void *, half, "[4 n_half] reals: unit normal n, offset") \
    X(double, coll_gain, "CollisionLimit.gain") \
    X(double, coll_min, "CollisionLimit.minimum_distance") \
    X(double, coll_detect, "CollisionLimit.detection_distance")

#define DK_VDECLARE(type, name, what) type name;
typedef struct dk_vel { DK_VEL_FIELDS(DK_VDECLARE) } dk_vel;
#undef DK_VDECLARE

DK_LAYOUT(vel, dk_vel, DK_VEL_FIELDS, DK_VEL_VERSION) /* dk_layout_vel, dk_names_vel (_native.c) */

int64_t dk_unchanged(const dk_watch *w); /* _native.c */

/* MuJoCo's mju_mat2Quat: the unit quaternion (w, x, y, z) of the rotation R (row-major 3 x 3). */
static void vel_mat2quat(const double R[9], double q[4]) {
    if (R[0] + R[4] + R[8] > 0) {
        q[0] = 0.5 * sqrt(1 + R[0] + R[4] + R[8]);
        q[1] = 0.25 * (R[7] - R[5]) / q[0];
        q[2] = 0.25 * (R[2] - R[6]) / q[0];
        q[3] = 0.25 * (R[3] - R[1]) / q[0];
    } else if (R[0] > R[4] && R[0] > R[8]) {
        q[1] = 0.5 * sqrt(1 + R[0] - R[4] - R[8]);
        q[0] = 0.25 * (R[7] - R[5]) / q[1];
        q[2] = 0.25 * (R[1] + R[3]) / q[1];
        q[3] = 0.25 * (R[2] + R[6]) / q[1];
    } else if (R[4] > R[8]) {
        q[2] = 0.5 * sqrt(1 - R[0] + R[4] - R[8]);
        q[0] = 0.25 * (R[2] - R[6]) / q[2];
        q[1] = 0.25 * (R[1] + R[3]) / q[2];
        q[3] = 0.25 * (R[5] + R[7]) / q[2];
    } else {
        q[3] = 0.5 * sqrt(1 - R[0] - R[4] + R[8]);
        q[0] = 0.25 * (R[3] - R[1]) / q[3];
        q[1] = 0.25 * (R[2] + R[6]) / q[3];
        q[2] = 0.25 * (R[5] + R[7]) / q[3];
    }
    const double nn = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    for (int i = 0; i < 4; i++) q[i] /= nn;
}

/* mink's SO3 log of the unit quaternion q (its C extension's so3_log): the rotation vector, w >= 0 taken,
 * zero where |(x, y, z)| < 1e-10. */
static void vel_so3_log(const double q[4], double w[3]) {
    const double sg = q[0] < 0 ? -1.0 : 1.0;
    double v[3] = {sg * q[1], sg * q[2], sg * q[3]};
    const double nn = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    if (nn < DK_LOG_EPS) { w[0] = w[1] = w[2] = 0; return; }
    const double ang = 2.0 * atan2(nn, sg * q[0]);
    for (int i = 0; i < 3; i++) w[i] = ang * (v[i] / nn);
}

static void vel_skew(const double x[3], double S[9]) {
    S[0] = 0, S[1] = -x[2], S[2] = x[1];
    S[3] = x[2], S[4] = 0, S[5] = -x[0];
    S[6] = -x[1], S[7] = x[0], S[8] = 0;
}

static void vel_mul3(const double A[9], const double B[9], double C[9]) {
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) C[3 * i + j] = A[3 * i] * B[j] + A[3 * i + 1] * B[3 + j] + A[3 * i + 2] * B[6 + j];
}

/* mink's SE3.log of (R as the unit quaternion q, p): e = [V^-1 p; w]. */
static void vel_se3_log(const double q[4], const double p[3], double e[6]) {
    double w[3], S[9], S2[9];
    vel_so3_log(q, w);
    const double t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
    vel_skew(w, S);
    vel_mul3(S, S, S2);
    double k;
    if (t2 < DK_LOG_EPS) {
        k = 1.0 / 12.0;
    } else {
        const double t = sqrt(t2), h = 0.5 * t;
        k = (1.0 - t * cos(h) / (2.0 * sin(h))) / t2;
    }
    for (int i = 0; i < 3; i++) {
        double acc = 0;
        for (int j = 0; j < 3; j++) acc += ((i == j) - 0.5 * S[3 * i + j] + k * S2[3 * i + j]) * p[j];
        e[i] = acc;
        e[3 + i] = w[i];
    }
}

/* mink's SE3.ljacinv(c) (Sola's (179b) with Q of (180)) into M (6 x 6 row-major): the identity where
 * |c_w|^2 < 1e-10. */
static void vel_ljacinv(const double c[6], double M[36]) {
    for (int i = 0; i < 36; i++) M[i] = (i % 7) == 0;
    const double t2 = c[3] * c[3] + c[4] * c[4] + c[5] * c[5];
    if (t2 < DK_LOG_EPS) return;
    const double t = sqrt(t2), st = sin(t), ct = cos(t);
    /* _getQ (the Taylor branch is unreachable past the switch above) */
    const double A = 0.5, B = (t - st) / (t2 * t), C = (1.0 - t2 / 2.0 - ct) / (t2 * t2);
    const double D = (2 * t - 3 * st + t * ct) / (2 * t2 * t2 * t);
    double V[9], Wm[9], VW[9], WV[9], WVW[9], VWW[9], X[9], Y[9], Q[9];
    vel_skew(c, V);
    vel_skew(c + 3, Wm);
    vel_mul3(V, Wm, VW);
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) WV[3 * i + j] = VW[3 * j + i];
    vel_mul3(WV, Wm, WVW);
    vel_mul3(VW, Wm, VWW);
    vel_mul3(WVW, Wm, X);
    vel_mul3(Wm, WVW, Y);
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            const int ij = 3 * i + j, ji = 3 * j + i;
            Q[ij] = A * V[ij] + B * (WV[ij] + VW[ij] + WVW[ij]) - C * (VWW[ij] - VWW[ji] - 3 * WVW[ij]) +
                    D * (X[ij] + Y[ij]);
        }
    /* SO3.ljacinv(w) (its Taylor branch, t < 1e-10, is unreachable here) */
    const double a = (1.0 / t2) * (1.0 - (t * st / (2.0 * (1.0 - ct))));
    double Ji[9], W2[9], JQ[9], JQJ[9];
    vel_mul3(Wm, Wm, W2);
    for (int i = 0; i < 9; i++) Ji[i] = ((i % 4) == 0) - 0.5 * Wm[i] + a * W2[i];
    vel_mul3(Ji, Q, JQ);
    vel_mul3(JQ, Ji, JQJ);
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            M[6 * i + j] = Ji[3 * i + j];
            M[6 * i + 3 + j] = -JQJ[3 * i + j];
            M[6 * (3 + i) + j] = 0;
            M[6 * (3 + i) + 3 + j] = Ji[3 * i + j];
        }
}

/* The frame task's error e (6) and ljacinv(e) (6 x 6) of the end pose (R_b row-major 3 x 3, p_b) against
 * the target T_t (4 x 4 row-major), through quaternions as mink's SE3 objects compute them. */
static void vel_frame_error(const double Rb[9], const double pb[3], const double Tt[16], double e[6],
                            double M[36]) {
    const double Rt[9] = {Tt[0], Tt[1], Tt[2], Tt[4], Tt[5], Tt[6], Tt[8], Tt[9], Tt[10]};
    double qb[4], qt[4];
    vel_mat2quat(Rb, qb);
    vel_mat2quat(Rt, qt);
    /* T_b^-1 T_t: rotation conj(qb) (x) qt, translation R_b^T (p_t - p_b) */
    const double a0 = qb[0], a1 = -qb[1], a2 = -qb[2], a3 = -qb[3];
    const double q[4] = {a0 * qt[0] - a1 * qt[1] - a2 * qt[2] - a3 * qt[3],
                         a0 * qt[1] + a1 * qt[0] + a2 * qt[3] - a3 * qt[2],
                         a0 * qt[2] - a1 * qt[3] + a2 * qt[0] + a3 * qt[1],
                         a0 * qt[3] + a1 * qt[2] - a2 * qt[1] + a3 * qt[0]};
    const double d[3] = {Tt[3] - pb[0], Tt[7] - pb[1], Tt[11] - pb[2]};
    double p[3];
    for (int i = 0; i < 3; i++) p[i] = Rb[i] * d[0] + Rb[3 + i] * d[1] + Rb[6 + i] * d[2];
    vel_se3_log(q, p, e);
    vel_ljacinv(e, M);
}

/* MuJoCo's mju_subQuat(res, qa, qb) as mj_differentiatePos uses it: the angular velocity w with
 * qb (x) exp(w / 2) = qa (the shortest rotation, dt = 1); qa, qb not necessarily unit. */
static void vel_sub_quat(const double qa[4], const double qb[4], double w[3]) {
    double a[4], b[4], na = 0, nb = 0;
    for (int i = 0; i < 4; i++) { na += qa[i] * qa[i]; nb += qb[i] * qb[i]; }
    na = sqrt(na), nb = sqrt(nb);
    for (int i = 0; i < 4; i++) {
        a[i] = na > 0 ? qa[i] / na : (i == 0);
        b[i] = nb > 0 ? qb[i] / nb : (i == 0);
    }
    /* conj(b) (x) a */
    const double d0 = b[0] * a[0] + b[1] * a[1] + b[2] * a[2] + b[3] * a[3];
    const double d1 = b[0] * a[1] - b[1] * a[0] - b[2] * a[3] + b[3] * a[2];
    const double d2 = b[0] * a[2] + b[1] * a[3] - b[2] * a[0] - b[3] * a[1];
    const double d3 = b[0] * a[3] - b[1] * a[2] + b[2] * a[1] - b[3] * a[0];
    const double s = sqrt(d1 * d1 + d2 * d2 + d3 * d3);
    if (s == 0) { w[0] = w[1] = w[2] = 0; return; }
    double ang = 2 * atan2(s, d0);
    if (ang > M_PI) ang -= 2 * M_PI; /* mju_quat2Vel */
    w[0] = d1 * ang / s, w[1] = d2 * ang / s, w[2] = d3 * ang / s;
}

/* Solve A x = b in place (x overwrites b) for symmetric positive definite A (d x d, row-major, overwritten
 * by its Cholesky factor); pivots clamped to a tiny positive value, as in kernels/dls.py. The QP's free
 * block is small (d <= nv), one row at a time: the scalar twin of _native_solve.c's spd_solve_lanes. */
static void vel_spd_solve(double *A, double *b, int d) {
    const double tiny = sqrt(2.2250738585072014e-308);
    double inv[d > 0 ? d : 1];
    for (int j = 0; j < d; j++) {
        double sjj = A[j * d + j];
        for (int k = 0; k < j; k++) sjj -= A[j * d + k] * A[j * d + k];
        const double ljj = sqrt(sjj > tiny ? sjj : tiny);
        inv[j] = 1 / ljj;
        A[j * d + j] = ljj;
        for (int i = j + 1; i < d; i++) {
            double sij = A[i * d + j];
            for (int k = 0; k < j; k++) sij -= A[i * d + k] * A[j * d + k];
            A[i * d + j] = sij * inv[j];
        }
    }
    for (int i = 0; i < d; i++) { /* L y = b */
        double v = b[i];
        for (int k = 0; k < i; k++) v -= A[i * d + k] * b[k];
        b[i] = v * inv[i];
    }
    for (int i = d - 1; i >= 0; i--) { /* L^T x = y */
        double v = b[i];
        for (int k = i + 1; k < d; k++) v -= A[k * d + i] * b[k];
        b[i] = v * inv[i];
    }
}

/* The minimiser of 1/2 x^T H x + c^T x over the free variables (fixed[i] == 0) with the others held at x:
 * H_FF xs_F = -(c_F + H_FB x_B) by Cholesky (L: work space); fr gets the free indices; returns their count. */
static int vel_qp_free(int d, const double *H, const double *c, const double *x, const int8_t *fixed, double *L,
                       double *xs, int *fr) {
    int nf = 0;
    for (int i = 0; i < d; i++)
        if (!fixed[i]) fr[nf++] = i;
    for (int a = 0; a < nf; a++) {
        const int i = fr[a];
        double r = -c[i];
        for (int j = 0; j < d; j++)
            if (fixed[j]) r -= H[i * d + j] * x[j];
        xs[a] = r;
        for (int b = 0; b <= a; b++) L[a * nf + b] = L[b * nf + a] = H[i * d + fr[b]];
    }
    vel_spd_solve(L, xs, nf);
    return nf;
}

/* The multiplier of the bound that holds variable i (fixed[i] = -1 or 1): >= 0 at the optimum. */
static inline double vel_qp_multiplier(int d, const double *H, const double *c, const double *x, int i, int side) {
    double gi = c[i];
    for (int j = 0; j < d; j++) gi += H[i * d + j] * x[j];
    return side < 0 ? gi : -gi;
}

/* The exact minimiser x of 1/2 x^T H x + c^T x over lo <= x <= hi (lo <= hi; H (d x d) symmetric positive
 * definite). First the primal-dual active-set iteration (Hintermueller, Ito and Kunisch 2002; Kunisch and
 * Rendl 2003): solve with the current bounds held, then hold every free variable that left its range and
 * release every held one whose multiplier is negative, all at once; unchanged sets satisfy the KKT
 * conditions (2-3 solves where bounds are active). It may cycle on matrices far from diagonal, so after 8
 * rounds a primal active-set method takes over from the clamped point (steps to the free block's minimiser
 * stopped at the first bound crossed, releases one wrong-signed multiplier at a time: finite). L (d x d),
 * xs (d), fixed, fr (d) are work space. Returns 1 when the KKT conditions hold, 0 after the iteration
 * limit. */
static int vel_box_qp(int d, const double *H, const double *c, const double *lo, const double *hi, double *x, double *L,
                      double *xs, int8_t *fixed, int *fr) {
    const double eps = 1e-13;
    double scale = 1;
    for (int i = 0; i < d; i++) {
        fixed[i] = lo[i] == hi[i] ? 2 : 0; /* 2: an equality, held for good; -1 / 1: held at lo / hi */
        x[i] = lo[i] == hi[i] ? lo[i] : 0;
        const double ac = fabs(c[i]), ah = H[i * d + i];
        scale = ac > scale ? ac : scale;
        scale = ah > scale ? ah : scale;
    }
    for (int round = 0; round < 8; round++) { /* primal-dual active set */
        const int nf = vel_qp_free(d, H, c, x, fixed, L, xs, fr);
        for (int a = 0; a < nf; a++) x[fr[a]] = xs[a];
        double xm = 0;
        for (int i = 0; i < d; i++) xm = fabs(x[i]) > xm ? fabs(x[i]) : xm;
        const double tol = eps * scale * (1 + xm);
        int changed = 0;
        for (int i = 0; i < d; i++) {
            if (fixed[i] == 0) {
                if (x[i] < lo[i]) { fixed[i] = -1; changed = 1; }
                else if (x[i] > hi[i]) { fixed[i] = 1; changed = 1; }
            } else if (fixed[i] != 2 && vel_qp_multiplier(d, H, c, x, i, fixed[i]) < -tol) {
                fixed[i] = 0;
                changed = 1;
            }
        }
        for (int i = 0; i < d; i++)
            if (fixed[i] == -1 || fixed[i] == 1) x[i] = fixed[i] < 0 ? lo[i] : hi[i];
        if (!changed) return 1;
    }
    for (int i = 0; i < d; i++) { /* primal active set from the clamped point, held where clamped */
        if (fixed[i] == 2) continue;
        x[i] = x[i] < lo[i] ? lo[i] : (x[i] > hi[i] ? hi[i] : x[i]);
        fixed[i] = x[i] == lo[i] ? -1 : (x[i] == hi[i] ? 1 : 0);
    }
    for (int it = 0; it < 4 * d + 16; it++) {
        const int nf = vel_qp_free(d, H, c, x, fixed, L, xs, fr);
        double alpha = 1;
        int block = -1, side = 0;
        for (int a = 0; a < nf; a++) { /* the longest feasible part of the step to xs */
            const int i = fr[a];
            const double step = xs[a] - x[i];
            if (xs[a] < lo[i] && step < 0) {
                const double t = (lo[i] - x[i]) / step;
                if (block < 0 || t < alpha) { alpha = t; block = i; side = -1; }
            } else if (xs[a] > hi[i] && step > 0) {
                const double t = (hi[i] - x[i]) / step;
                if (block < 0 || t < alpha) { alpha = t; block = i; side = 1; }
            }
        }
        alpha = alpha > 0 ? alpha : 0;
        for (int a = 0; a < nf; a++) {
            const int i = fr[a];
            x[i] = block < 0 ? xs[a] : x[i] + alpha * (xs[a] - x[i]);
            x[i] = x[i] < lo[i] ? lo[i] : (x[i] > hi[i] ? hi[i] : x[i]);
        }
        if (block >= 0) { /* a bound crossed: it is held from now on */
            fixed[block] = (int8_t)side;
            x[block] = side < 0 ? lo[block] : hi[block];
            continue;
        }
        double xm = 0, worst = 0;
        for (int i = 0; i < d; i++) xm = fabs(x[i]) > xm ? fabs(x[i]) : xm;
        const double tol = eps * scale * (1 + xm);
        int release = -1;
        for (int i = 0; i < d; i++) {
            if (fixed[i] != -1 && fixed[i] != 1) continue;
            const double lam = vel_qp_multiplier(d, H, c, x, i, fixed[i]);
            if (lam < -tol && lam < worst) { worst = lam; release = i; }
        }
        if (release < 0) return 1;
        fixed[release] = 0;
    }
    return 0;
}

/* Cholesky factor L L^T = A in place (lower triangle, d x d row-major), pivots clamped to a tiny positive
 * value as in vel_spd_solve; vel_lsolve / vel_ltsolve: L y = b and L^T y = b in place. */
static void vel_chol(double *A, int d) {
    const double tiny = sqrt(2.2250738585072014e-308);
    for (int j = 0; j < d; j++) {
        double sjj = A[j * d + j];
        for (int k = 0; k < j; k++) sjj -= A[j * d + k] * A[j * d + k];
        const double ljj = sqrt(sjj > tiny ? sjj : tiny);
        A[j * d + j] = ljj;
        for (int i = j + 1; i < d; i++) {
            double sij = A[i * d + j];
            for (int k = 0; k < j; k++) sij -= A[i * d + k] * A[j * d + k];
            A[i * d + j] = sij / ljj;
        }
    }
}

static void vel_lsolve(const double *L, int d, double *b) {
    for (int i = 0; i < d; i++) {
        double v = b[i];
        for (int k = 0; k < i; k++) v -= L[i * d + k] * b[k];
        b[i] = v / L[i * d + i];
    }
}

static void vel_ltsolve(const double *L, int d, double *b) {
    for (int i = d - 1; i >= 0; i--) {
        double v = b[i];
        for (int k = i + 1; k < d; k++) v -= L[k * d + i] * b[k];
        b[i] = v / L[i * d + i];
    }
}

/* Constraint k of vel_rows_qp's reduced problem (nf free variables): k < m row k of Gr (m x nf), bound
 * hb[k]; k = m + 2a: x_a <= hi_a; k = m + 2a + 1: -x_a <= -lo_a. Its vector into a; returns its bound. */
static double vel_row_of(int64_t k, int64_t m, int nf, const double *Gr, const double *hb, const double *lo,
                         const double *hi, const int *fr, double *a) {
    if (k < m) {
        for (int i = 0; i < nf; i++) a[i] = Gr[k * nf + i];
        return hb[k];
    }
    const int i = (int)((k - m) / 2), up = (int)((k - m) % 2) == 0;
    for (int j = 0; j < nf; j++) a[j] = 0;
    a[i] = up ? 1 : -1;
    return up ? hi[fr[i]] : -lo[fr[i]];
}

/* The exact minimiser x of 1/2 x^T H x + c^T x (H d x d symmetric positive definite) over lo <= x <= hi and
 * the m rows G x <= h (G m x d row-major, h finite), given in x the minimiser over the box alone (vel_box_qp):
 * where that meets every row it is the answer (the box path's cost: one product with G). Else the dual
 * active-set method of Goldfarb and Idnani (1983) on the free variables (lo < hi; the others held), the box
 * bounds as rows: from the unconstrained minimiser, the most violated constraint is added with the primal
 * step z = -H^-1 (a_p - N r) and the active multipliers moving by -r (r = S^-1 N^T H^-1 a_p, S = N^T H^-1 N),
 * a constraint whose multiplier reaches 0 first dropped (a partial step); every iterate is the minimiser
 * over its active set, the multipliers stay >= 0, so the method ends at the KKT point (finite), or finds no
 * feasible point. The last active set's KKT system is then solved once more from the start (no rounding
 * carried over the steps). Linear algebra on L (H = L L^T) and B = L^-1 N, S = B^T B. Returns 1 with x the
 * minimiser, 0 (x left as given) when the rows and the box leave no feasible point or the iteration limit
 * is reached. */
static int vel_rows_qp(int d, const double *H, const double *c, const double *lo, const double *hi, int64_t m,
                       const double *G, const double *h, double *x) {
    const double eps = 1e-12;
    int viol = 0;
    for (int64_t k = 0; k < m && !viol; k++) {
        double gx = 0, ga = 0;
        for (int j = 0; j < d; j++) {
            gx += G[k * d + j] * x[j];
            ga += fabs(G[k * d + j] * x[j]);
        }
        viol = gx - h[k] > eps * (1 + fabs(h[k]) + ga);
    }
    if (!viol) return 1;
    int fr[d > 0 ? d : 1], nf = 0;
    double xb[d > 0 ? d : 1];
    for (int i = 0; i < d; i++) {
        xb[i] = lo[i] == hi[i] ? lo[i] : 0;
        if (lo[i] != hi[i]) fr[nf++] = i;
    }
    const int n1 = nf > 0 ? nf : 1;
    double *mem = malloc(sizeof(double) * ((size_t)m * n1 + (size_t)m + 4 * (size_t)n1 * n1 + 10 * (size_t)n1));
    if (!mem) return 0;
    double *Gr = mem, *hb = Gr + (size_t)m * n1, *L = hb + m, *Bm = L + (size_t)n1 * n1, *S = Bm + (size_t)n1 * n1;
    double *Ls = S + (size_t)n1 * n1, *g0 = Ls + (size_t)n1 * n1, *xr = g0 + n1, *u = xr + n1, *w = u + n1;
    double *r = w + n1, *y = r + n1, *z = y + n1, *ap = z + n1, *tq = ap + n1, *tq2 = tq + n1;
    int act[n1];
    for (int a = 0; a < nf; a++) {
        const int i = fr[a];
        double ci = c[i];
        for (int j = 0; j < d; j++)
            if (lo[j] == hi[j]) ci += H[i * d + j] * xb[j];
        g0[a] = ci;
        for (int b = 0; b < nf; b++) L[a * nf + b] = H[i * d + fr[b]];
    }
    for (int64_t k = 0; k < m; k++) {
        double v = h[k];
        for (int j = 0; j < d; j++)
            if (lo[j] == hi[j]) v -= G[k * d + j] * xb[j];
        hb[k] = v;
        for (int a = 0; a < nf; a++) Gr[k * nf + a] = G[k * d + fr[a]];
    }
    vel_chol(L, nf);
    vel_lsolve(L, nf, g0); /* g0 = L^-1 c_r */
    for (int a = 0; a < nf; a++) xr[a] = -g0[a];
    vel_ltsolve(L, nf, xr); /* the unconstrained minimiser */
    const int64_t nc = m + 2 * (int64_t)nf;
    int q = 0, ok = 0;
    int64_t it = 0;
    const int64_t cap = 8 * nc + 32;
    /* S = B^T B over the active set, factored (Ls), and r = S^-1 B^T w for the vector w */
#define VEL_ACTIVE_SOLVE(wv, rv)                                                                           \
    do {                                                                                                   \
        for (int i2 = 0; i2 < q; i2++) {                                                                   \
            double acc = 0;                                                                                \
            for (int k2 = 0; k2 < nf; k2++) acc += Bm[(size_t)i2 * n1 + k2] * (wv)[k2];                     \
            (rv)[i2] = acc;                                                                                \
            for (int j2 = 0; j2 <= i2; j2++) {                                                             \
                double s2 = 0;                                                                             \
                for (int k2 = 0; k2 < nf; k2++) s2 += Bm[(size_t)i2 * n1 + k2] * Bm[(size_t)j2 * n1 + k2]; \
                Ls[i2 * q + j2] = s2;                                                                      \
            }                                                                                              \
        }                                                                                                  \
        vel_chol(Ls, q);                                                                                   \
        vel_lsolve(Ls, q, (rv));                                                                           \
        vel_ltsolve(Ls, q, (rv));                                                                          \
    } while (0)
    for (;;) {
        int64_t p = -1;
        double worst = 0;
        for (int64_t k = 0; k < nc; k++) { /* the most violated inactive constraint */
            int on = 0;
            for (int i = 0; i < q && !on; i++) on = act[i] == k;
            if (on) continue;
            const double bk = vel_row_of(k, m, nf, Gr, hb, lo, hi, fr, ap);
            if (!isfinite(bk)) continue;
            double ax = 0, aa = 0;
            for (int i = 0; i < nf; i++) {
                ax += ap[i] * xr[i];
                aa += fabs(ap[i] * xr[i]);
            }
            const double vk = ax - bk;
            if (vk > eps * (1 + fabs(bk) + aa) && vk > worst) { worst = vk; p = k; }
        }
        if (p < 0) { ok = 1; break; }
        const double bp = vel_row_of(p, m, nf, Gr, hb, lo, hi, fr, ap);
        double up = 0;
        int added = 0;
        while (!added) {
            if (++it > cap) goto done;
            for (int i = 0; i < nf; i++) w[i] = ap[i];
            vel_lsolve(L, nf, w);
            VEL_ACTIVE_SOLVE(w, r);
            double yy = 0, ww = 0;
            for (int i = 0; i < nf; i++) {
                double v = w[i];
                for (int k = 0; k < q; k++) v -= Bm[(size_t)k * n1 + i] * r[k];
                y[i] = v;
                yy += v * v;
                ww += w[i] * w[i];
            }
            const int dependent = !(yy > 1e-20 * ww);
            double t1 = INFINITY, t2 = INFINITY;
            int kb = -1;
            if (!dependent) {
                double ax = 0;
                for (int i = 0; i < nf; i++) ax += ap[i] * xr[i];
                t1 = (ax - bp) / yy;
                t1 = t1 > 0 ? t1 : 0;
            }
            for (int i = 0; i < q; i++)
                if (r[i] > 0 && u[i] / r[i] < t2) { t2 = u[i] / r[i]; kb = i; }
            if (!isfinite(t1) && !isfinite(t2)) goto done; /* no feasible point */
            const double t = t1 < t2 ? t1 : t2;
            if (!dependent) {
                for (int i = 0; i < nf; i++) z[i] = -y[i];
                vel_ltsolve(L, nf, z);
                for (int i = 0; i < nf; i++) xr[i] += t * z[i];
            }
            for (int i = 0; i < q; i++) u[i] -= t * r[i];
            up += t;
            if (t1 <= t2) { /* a full step: p joins the active set */
                act[q] = (int)p;
                u[q] = up;
                for (int i = 0; i < nf; i++) Bm[(size_t)q * n1 + i] = w[i];
                q++;
                added = 1;
            } else { /* a partial step: constraint kb leaves */
                for (int i = kb; i + 1 < q; i++) {
                    act[i] = act[i + 1];
                    u[i] = u[i + 1];
                    for (int k = 0; k < nf; k++) Bm[(size_t)i * n1 + k] = Bm[(size_t)(i + 1) * n1 + k];
                }
                q--;
            }
        }
    }
done:
    if (ok) { /* the final active set's KKT point from the start: u = S^-1 (-B^T g0 - b_A), x = -L^-T (g0 + B u) */
        for (int i = 0; i < nf; i++) tq2[i] = -g0[i];
        VEL_ACTIVE_SOLVE(tq2, tq); /* S^-1 (-B^T g0) */
        for (int i = 0; i < q; i++) {
            const double bk = vel_row_of(act[i], m, nf, Gr, hb, lo, hi, fr, ap);
            r[i] = bk;
        }
        vel_lsolve(Ls, q, r);
        vel_ltsolve(Ls, q, r); /* S^-1 b_A */
        for (int i = 0; i < nf; i++) {
            double v = g0[i];
            for (int k = 0; k < q; k++) v += Bm[(size_t)k * n1 + i] * (tq[k] - r[k]);
            z[i] = -v;
        }
        vel_ltsolve(L, nf, z);
        for (int i = 0; i < d; i++) x[i] = xb[i];
        for (int a = 0; a < nf; a++) x[fr[a]] = z[a];
    }
#undef VEL_ACTIVE_SOLVE
    free(mem);
    return ok;
}

#define DK_VEL_PASS 1
#else
#undef DK_VEL_PASS
#define DK_VEL_PASS 2
#endif

typedef struct { /* one call's fixed inputs, read once */
    const dk_vel *v;
    Shape s;
    DK(Params) pp;
    Space sp;
    int F, nv, n;
    const int32_t *fend;
    const real *fcost, *fgain, *flm, *pcost, *plo, *phi, *vmax;
    real pgain, plm, lgain, dt, damping;
} DK(Vel);

/* Doubles of one thread's QP work space: H, L (nv x nv), c, lo, hi, x, xs (nv), A (6 x nv). */
static size_t DK(vel_qp_reals)(int nv) {
    return (size_t)2 * nv * nv + (size_t)13 * nv + 16;
}

/* Lane l's pose of frame f (-1: the base) in the FK block: R (row-major 3 x 3) and t. */
static void DK(vel_frame)(const DK(Scratch) *sc, int l, int f, double R[9], double t[3]) {
    const real *E = f < 0 ? sc->basef : sc->F + (size_t)f * 12 * W;
    for (int r = 0; r < 3; r++) {
        for (int cc = 0; cc < 3; cc++) R[3 * r + cc] = (double)E[(4 * r + cc) * W + l];
        t[r] = (double)E[(4 * r + 3) * W + l];
    }
}

/* w times the linear rows of the Jacobian (3.30) of the point p (base frame) moving with frame f (lane l):
 * DK(column) of every joint from f to the base, each column written to t6 and added. dir NULL: into out
 * (3 x nv row-major); else dir . those rows into out (nv). */
static void DK(vel_point_columns)(const DK(Vel) *V, const DK(Scratch) *sc, int l, int f, const double p[3],
                                  const double *dir, double w, double *out) {
    const Shape *s = &V->s;
    const int nv = s->nv;
    real E[12 * W], t6[6];
    E[3 * W] = (real)p[0], E[7 * W] = (real)p[1], E[11 * W] = (real)p[2];
    for (int j = f; j >= 0; j = s->parent[j]) {
        const real *Aj = (s->has_post[j] ? sc->A : sc->F) + (size_t)j * 12 * W + l;
        const int mo = s->motion[j], naxes = mo == DK_MOTION_S ? 3 : 1;
        for (int ax = 0; ax < naxes; ax++) {
            if (mo == DK_MOTION_S) DK(column)(Aj, E, 1, 1, 1, ax, t6, 1, 1);
            else if (mo == DK_MOTION_R) DK(column)(Aj, E, V->pp.mult[j], 1, 1, 2, t6, 1, 1);
            else DK(column)(Aj, E, V->pp.mult[j], 0, 1, 2, t6, 1, 1);
            const int col = s->vidx[j] + ax;
            if (dir) out[col] += w * (dir[0] * (double)t6[0] + dir[1] * (double)t6[1] + dir[2] * (double)t6[2]);
            else
                for (int r = 0; r < 3; r++) out[(size_t)r * nv + col] += w * (double)t6[r];
        }
    }
}

/* The ComTask's terms of (T.1) added to H (lower triangle) and c: e = p_C(q) - target, J = J_C, the
 * centre of mass of the bodies and its Jacobian sum_i w_i J_P(p_i) (center_of_mass.py: p_i = F_i c_i,
 * w_i = m_i / M), A = C J, b = -gain C e, mu = lm_damping |b|^2. The Jacobian by subtrees: joint j moves
 * the bodies below its frame, whose weight W_j and weighted centre S_j / W_j are summed from the leaves up
 * (parents precede children), so its column is W_j times the point column (DK(column)) at S_j / W_j: one
 * column per joint, not one per body and ancestor. */
static void DK(vel_com)(const DK(Vel) *V, const DK(Scratch) *sc, int l, const real *target, double *H, double *c) {
    const dk_vel *v = V->v;
    const Shape *s = &V->s;
    const int nv = V->nv, B = (int)v->n_bodies, J = s->J;
    const real *bp = (const real *)v->body_point, *bw = (const real *)v->body_weight;
    const real *cost = (const real *)v->com_cost;
    double com[3] = {0, 0, 0}, Jc[3 * (nv > 0 ? nv : 1)], Sw[4 * (J > 0 ? J : 1)]; /* S_j (3), W_j */
    for (int i = 0; i < 3 * nv; i++) Jc[i] = 0;
    for (int i = 0; i < 4 * J; i++) Sw[i] = 0;
    for (int i = 0; i < B; i++) {
        double R[9], t[3], pi[3];
        const int f = v->body_frame[i];
        DK(vel_frame)(sc, l, f, R, t);
        const double wi = (double)bw[i];
        for (int r = 0; r < 3; r++) {
            pi[r] = R[3 * r] * (double)bp[3 * i] + R[3 * r + 1] * (double)bp[3 * i + 1] +
                    R[3 * r + 2] * (double)bp[3 * i + 2] + t[r];
            com[r] += wi * pi[r];
            if (f >= 0) Sw[4 * f + r] += wi * pi[r];
        }
        if (f >= 0) Sw[4 * f + 3] += wi;
    }
    for (int j = J - 1; j >= 0; j--) { /* subtree sums, then each joint's column */
        const int pj = s->parent[j];
        if (pj >= 0)
            for (int r = 0; r < 4; r++) Sw[4 * pj + r] += Sw[4 * j + r];
        const double Wj = Sw[4 * j + 3];
        if (!(Wj > 0)) continue;
        const double pc[3] = {Sw[4 * j] / Wj, Sw[4 * j + 1] / Wj, Sw[4 * j + 2] / Wj};
        real E[12 * W], t6[6];
        E[3 * W] = (real)pc[0], E[7 * W] = (real)pc[1], E[11 * W] = (real)pc[2];
        const real *Aj = (s->has_post[j] ? sc->A : sc->F) + (size_t)j * 12 * W + l;
        const int mo = s->motion[j], naxes = mo == DK_MOTION_S ? 3 : 1;
        for (int ax = 0; ax < naxes; ax++) {
            if (mo == DK_MOTION_S) DK(column)(Aj, E, 1, 1, 1, ax, t6, 1, 1);
            else if (mo == DK_MOTION_R) DK(column)(Aj, E, V->pp.mult[j], 1, 1, 2, t6, 1, 1);
            else DK(column)(Aj, E, V->pp.mult[j], 0, 1, 2, t6, 1, 1);
            const int col = s->vidx[j] + ax;
            for (int r = 0; r < 3; r++) Jc[(size_t)r * nv + col] += Wj * (double)t6[r];
        }
    }
    double b[3], mu = 0;
    for (int a = 0; a < 3; a++) {
        b[a] = (double)cost[a] * (-(double)v->com_gain * (com[a] - (double)target[a]));
        mu += b[a] * b[a];
        for (int i = 0; i < nv; i++) Jc[(size_t)a * nv + i] *= (double)cost[a];
    }
    mu *= (double)v->com_lm;
    for (int i = 0; i < nv; i++) {
        c[i] -= Jc[i] * b[0] + Jc[nv + i] * b[1] + Jc[2 * nv + i] * b[2];
        for (int j = 0; j <= i; j++)
            H[i * nv + j] += Jc[i] * Jc[j] + Jc[nv + i] * Jc[nv + j] + Jc[2 * nv + i] * Jc[2 * nv + j];
        H[i * nv + i] += mu;
    }
}

/* Entry e of the CollisionLimit's distances (lane l; caps: the placed capsules, 6 per capsule, its ends in
 * the base frame): e < P the self pair e, then per capsule g its world objects (round ones, then
 * half-spaces). d: the signed distance (capsule-capsule: |c1 - c2| - r1 - r2 at Ericson's closest points,
 * DK(segment_closest) of _native_collide.c; half-space: min(n.a, n.b) - offset - r). With grad (nv, added
 * to): dd/dq = n . (J_P(c1) - J_P(c2)), n = (c1 - c2) / |c1 - c2| (the envelope theorem, as
 * collision/distances.py; 0 at coincident centres). Returns 0 for an entry not checked (a fixed capsule's
 * world rows). */
static int DK(vel_entry)(const DK(Vel) *V, const DK(Scratch) *sc, int l, const double *caps, int64_t e, double *d,
                         double *grad) {
    const dk_vel *v = V->v;
    const int64_t P = v->n_pairs, O = v->n_round + v->n_half;
    const real *cr = (const real *)v->cap_r;
    int g, f2 = -2;
    double p1[3], u1[3], p2[3], u2[3], r2;
    if (e < P) {
        const int j = v->pair_j[e];
        g = v->pair_i[e];
        f2 = v->cap_frame[j];
        for (int k = 0; k < 3; k++) { p2[k] = caps[6 * j + k]; u2[k] = caps[6 * j + 3 + k] - p2[k]; }
        r2 = (double)cr[j];
    } else {
        g = (int)((e - P) / O);
        const int64_t o = (e - P) % O;
        if (!v->cap_moving[g]) return 0;
        if (o >= v->n_round) { /* a half-space */
            const real *hs = (const real *)v->half + 4 * (o - v->n_round);
            const double n[3] = {(double)hs[0], (double)hs[1], (double)hs[2]};
            const double *A = caps + 6 * g, *B = A + 3;
            const double da = n[0] * A[0] + n[1] * A[1] + n[2] * A[2], db = n[0] * B[0] + n[1] * B[1] + n[2] * B[2];
            *d = (da < db ? da : db) - (double)hs[3] - (double)cr[g];
            if (grad) DK(vel_point_columns)(V, sc, l, v->cap_frame[g], da < db ? A : B, n, 1, grad);
            return 1;
        }
        const real *ra = (const real *)v->round_a + 3 * o, *rb = (const real *)v->round_b + 3 * o;
        for (int k = 0; k < 3; k++) { p2[k] = (double)ra[k]; u2[k] = (double)rb[k] - (double)ra[k]; }
        r2 = (double)((const real *)v->round_r)[o];
    }
    for (int k = 0; k < 3; k++) { p1[k] = caps[6 * g + k]; u1[k] = caps[6 * g + 3 + k] - p1[k]; }
    real sp, tp;
    DK(segment_closest)((real)u1[0], (real)u1[1], (real)u1[2], (real)u2[0], (real)u2[1], (real)u2[2],
                        (real)(p1[0] - p2[0]), (real)(p1[1] - p2[1]), (real)(p1[2] - p2[2]), &sp, &tp);
    double c1[3], c2[3], n[3], nn = 0;
    for (int k = 0; k < 3; k++) {
        c1[k] = p1[k] + (double)sp * u1[k];
        c2[k] = p2[k] + (double)tp * u2[k];
        n[k] = c1[k] - c2[k];
        nn += n[k] * n[k];
    }
    nn = sqrt(nn);
    *d = nn - (double)cr[g] - r2;
    if (grad && nn > 0) {
        for (int k = 0; k < 3; k++) n[k] /= nn;
        DK(vel_point_columns)(V, sc, l, v->cap_frame[g], c1, n, 1, grad);
        if (f2 > -2) DK(vel_point_columns)(V, sc, l, f2, c2, n, -1, grad);
    }
    return 1;
}

/* The CollisionLimit (L.3) of lane l: the rows -J_d dq <= gain max(d - d_min, 0) of every distance
 * d < detection_distance, and x (the box QP's minimiser) re-solved with them where it breaks one
 * (vel_rows_qp). Returns ok. */
static int DK(vel_collision)(const DK(Vel) *V, const DK(Scratch) *sc, int l, const double *H, const double *c,
                             const double *lo, const double *hi, double *x) {
    const dk_vel *v = V->v;
    const int nv = V->nv, G = (int)v->n_caps;
    const int64_t total = v->n_pairs + (int64_t)G * (v->n_round + v->n_half);
    double caps[6 * G];
    for (int g = 0; g < G; g++) {
        double R[9], t[3];
        const real *a = (const real *)v->cap_a + 3 * g, *b = (const real *)v->cap_b + 3 * g;
        DK(vel_frame)(sc, l, v->cap_frame[g], R, t);
        for (int r = 0; r < 3; r++) {
            caps[6 * g + r] = R[3 * r] * (double)a[0] + R[3 * r + 1] * (double)a[1] + R[3 * r + 2] * (double)a[2] + t[r];
            caps[6 * g + 3 + r] = R[3 * r] * (double)b[0] + R[3 * r + 1] * (double)b[1] + R[3 * r + 2] * (double)b[2] + t[r];
        }
    }
    const double detect = v->coll_detect;
    int64_t m = 0;
    for (int64_t e = 0; e < total; e++) {
        double d;
        m += DK(vel_entry)(V, sc, l, caps, e, &d, NULL) && d < detect;
    }
    if (m == 0) return 1;
    double sbuf[2048];
    const size_t need = (size_t)m * (nv + 1);
    double *Gm = need <= 2048 ? sbuf : malloc(sizeof(double) * need);
    if (!Gm) return 0;
    double *h = Gm + (size_t)m * nv;
    int64_t k = 0;
    for (int64_t e = 0; e < total && k < m; e++) {
        double d;
        if (!DK(vel_entry)(V, sc, l, caps, e, &d, NULL) || !(d < detect)) continue;
        double *row = Gm + (size_t)k * nv;
        for (int i = 0; i < nv; i++) row[i] = 0;
        DK(vel_entry)(V, sc, l, caps, e, &d, row);
        for (int i = 0; i < nv; i++) row[i] = -row[i];
        h[k++] = v->coll_gain * (d > v->coll_min ? d - v->coll_min : 0);
    }
    const int ok = vel_rows_qp(nv, H, c, lo, hi, m, Gm, h, x);
    if (Gm != sbuf) free(Gm);
    return ok;
}

/* The step of one row: the FK block's lane l (sc: ends and Jacobians), q (nq), its targets (F x 16) and
 * q_ref (nq) -> v (nv), q_next (nq, or NULL); returns ok. */
static int DK(vel_row)(const DK(Vel) *V, const DK(Scratch) *sc, int l, const real *q, const real *tgt,
                       const real *qref, real *vout, real *qnext, double *work, int8_t *fixed, int *fr,
                       const real *ctgt) {
    const int nv = V->nv;
    double *H = work, *L = H + (size_t)nv * nv, *c = L + (size_t)nv * nv, *lo = c + nv, *hi = lo + nv;
    double *x = hi + nv, *xs = x + nv, *A = xs + nv; /* A: 6 x nv */
    int ok = 1;
    for (int i = 0; i < nv * nv; i++) H[i] = 0;
    for (int i = 0; i < nv; i++) c[i] = 0;
    for (int f = 0; f < V->F; f++) {
        const int k = V->fend[f];
        const real *E = sc->ends + (size_t)k * 12 * W, *Jb = sc->Jb + (size_t)k * 6 * nv * W;
        double Rb[9], pb[3], Tt[16], e[6], M[36];
        for (int r = 0; r < 3; r++) {
            for (int cc = 0; cc < 3; cc++) Rb[3 * r + cc] = (double)E[(4 * r + cc) * W + l];
            pb[r] = (double)E[(4 * r + 3) * W + l];
        }
        for (int i = 0; i < 16; i++) Tt[i] = (double)tgt[16 * f + i];
        vel_frame_error(Rb, pb, Tt, e, M);
        const real *cost = V->fcost + 6 * f;
        const double gain = (double)V->fgain[f];
        double b[6], mu = 0;
        for (int a = 0; a < 6; a++) {
            b[a] = (double)cost[a] * (-gain * e[a]);
            mu += b[a] * b[a];
        }
        mu *= (double)V->flm[f];
        for (int i = 0; i < nv; i++) { /* A = -C M J_body, column by column */
            double jb[6];
            for (int a = 0; a < 3; a++) {
                double sv = 0, sw = 0;
                for (int r = 0; r < 3; r++) {
                    sv += Rb[3 * r + a] * (double)Jb[((size_t)r * nv + i) * W + l];
                    sw += Rb[3 * r + a] * (double)Jb[((size_t)(3 + r) * nv + i) * W + l];
                }
                jb[a] = sv, jb[3 + a] = sw;
            }
            for (int a = 0; a < 6; a++) {
                double acc = 0;
                for (int r = 0; r < 6; r++) acc += M[6 * a + r] * jb[r];
                A[(size_t)a * nv + i] = (double)cost[a] * -acc;
            }
        }
        for (int i = 0; i < nv; i++) {
            double ci = 0;
            for (int a = 0; a < 6; a++) ci -= A[(size_t)a * nv + i] * b[a];
            c[i] += ci;
            for (int j = 0; j <= i; j++) {
                double acc = 0;
                for (int a = 0; a < 6; a++) acc += A[(size_t)a * nv + i] * A[(size_t)a * nv + j];
                H[i * nv + j] += acc;
            }
            H[i * nv + i] += mu;
        }
    }
    if (V->pcost) { /* e = q (-) q_ref, J = I */
        double ep[nv > 0 ? nv : 1];
        for (int i = 0; i < nv; i++)
            if (V->sp.vq[i] >= 0) ep[i] = (double)q[V->sp.vq[i]] - (double)qref[V->sp.vq[i]];
        for (int bq = 0; bq < V->sp.nb; bq++) {
            double qa[4], qb[4], w[3];
            for (int cc = 0; cc < 4; cc++) {
                qa[cc] = (double)q[V->sp.qs[bq] + cc];
                qb[cc] = (double)qref[V->sp.qs[bq] + cc];
            }
            vel_sub_quat(qa, qb, w);
            for (int cc = 0; cc < 3; cc++) ep[V->sp.vs[bq] + cc] = w[cc];
        }
        double mu = 0;
        for (int i = 0; i < nv; i++) {
            const double ci = (double)V->pcost[i], b = ci * (-(double)V->pgain * ep[i]);
            mu += b * b;
            c[i] -= ci * b;
            H[i * nv + i] += ci * ci;
        }
        mu *= (double)V->plm;
        for (int i = 0; i < nv; i++) H[i * nv + i] += mu;
    }
    if (V->v->com_cost) DK(vel_com)(V, sc, l, ctgt, H, c); /* v3: the ComTask */
    for (int i = 0; i < nv; i++) {
        H[i * nv + i] += (double)V->damping;
        for (int j = 0; j < i; j++) H[j * nv + i] = H[i * nv + j];
    }
    const double inf = INFINITY;
    for (int i = 0; i < nv; i++) { /* the box: configuration and velocity limits */
        double plo = -inf, phi = inf, vlo = -inf, vhi = inf;
        const int qi = V->sp.vq[i];
        if (V->plo && qi >= 0) {
            plo = (double)V->lgain * ((double)V->plo[i] - (double)q[qi]);
            phi = (double)V->lgain * ((double)V->phi[i] - (double)q[qi]);
            if (plo > phi) plo = phi = 0.5 * (plo + phi);
        }
        if (V->vmax) vhi = (double)V->dt * (double)V->vmax[i], vlo = -vhi;
        double a = plo > vlo ? plo : vlo, b = phi < vhi ? phi : vhi;
        if (a > b) { /* no room: the velocity range's point nearest the position range */
            a = b = plo > vhi ? vhi : vlo;
            ok = 0;
        }
        lo[i] = a, hi[i] = b;
    }
    ok &= vel_box_qp(nv, H, c, lo, hi, x, L, xs, fixed, fr); /* in double for both real types */
    if (V->v->n_caps > 0) ok &= DK(vel_collision)(V, sc, l, H, c, lo, hi, x); /* v3: the CollisionLimit's rows */
    const double inv_dt = 1 / (double)V->dt;
    for (int i = 0; i < nv; i++) vout[i] = (real)(x[i] * inv_dt);
    if (qnext) { /* q (+) dq: scalars add, quaternions Q <- normalise(Q) (x) exp(w / 2) */
        for (int i = 0; i < V->n; i++) qnext[i] = q[i];
        for (int i = 0; i < nv; i++)
            if (V->sp.vq[i] >= 0) qnext[V->sp.vq[i]] = (real)((double)qnext[V->sp.vq[i]] + x[i]);
        for (int bq = 0; bq < V->sp.nb; bq++) {
            real *Q = qnext + V->sp.qs[bq];
            double x4[4], nn = 0;
            for (int cc = 0; cc < 4; cc++) { x4[cc] = (double)Q[cc]; nn += x4[cc] * x4[cc]; }
            nn = sqrt(nn);
            const int small = nn <= (double)DK_QSMALL;
            for (int cc = 0; cc < 4; cc++) x4[cc] = small ? (cc == 0) : x4[cc] / nn;
            const double *w = x + V->sp.vs[bq];
            const double wx = w[0], wy = w[1], wz = w[2];
            const double h = 0.5 * sqrt(wx * wx + wy * wy + wz * wz);
            const double e0 = cos(h), s = h < 1e-4 ? 0.5 * (1 - h * h / 6) : 0.5 * sin(h) / h;
            const double ev[3] = {s * wx, s * wy, s * wz};
            Q[0] = (real)(x4[0] * e0 - x4[1] * ev[0] - x4[2] * ev[1] - x4[3] * ev[2]);
            Q[1] = (real)(x4[0] * ev[0] + e0 * x4[1] + x4[2] * ev[2] - x4[3] * ev[1]);
            Q[2] = (real)(x4[0] * ev[1] + e0 * x4[2] + x4[3] * ev[0] - x4[1] * ev[2]);
            Q[3] = (real)(x4[0] * ev[2] + e0 * x4[3] + x4[1] * ev[1] - x4[2] * ev[0]);
        }
    }
    return ok;
}

/* Bytes of one thread's work: the FK scratch, then the QP's reals, then its index arrays. */
static size_t DK(vel_thread_bytes)(const Shape *s) {
    return (DK(scratch_size)(s) + sizeof(double) * DK(vel_qp_reals)(s->nv) + (size_t)s->nv * (sizeof(int) + 1) + 8 +
            63) / 64 * 64;
}

/* Bytes of a serial call's kept work space: the plans, the space's index arrays, one thread's work. */
static size_t DK(vel_keep_split)(const Shape *s, size_t *space_off, size_t *thread_off) {
    *space_off = (DK(params_bytes)(s) + 63) / 64 * 64;
    *thread_off = *space_off + ((size_t)(s->nv + 3 * s->n + 1) * sizeof(int32_t) + 63) / 64 * 64;
    return *thread_off + DK(vel_thread_bytes)(s);
}

static int64_t DK(velocity_work_bytes)(const dk_args *a) {
    Shape s;
    read_shape(a, &s);
    size_t so, to;
    return (int64_t)DK(vel_keep_split)(&s, &so, &to);
}

/* Rows blk * W .. of the call, one FK pass and one step per row. */
static void DK(vel_block)(const DK(Vel) *V, DK(Scratch) *sc, char *thread, int64_t blk, int64_t *bad) {
    const dk_vel *v = V->v;
    const int n = V->n, nv = V->nv;
    const int64_t B = v->batch, b0 = blk * W;
    const int nl = (int)(B - b0 < W ? B - b0 : W);
    const real *q = (const real *)v->q, *tgt = (const real *)v->target, *qref = (const real *)v->q_ref;
    double *work = (double *)(thread + DK(scratch_size)(&V->s));
    int8_t *fixed = (int8_t *)(work + DK(vel_qp_reals)(nv));
    int *fr = (int *)(((uintptr_t)(fixed + nv) + sizeof(int) - 1) / sizeof(int) * sizeof(int));
    *bad += DK(load_q)(&V->s, sc, q, b0, nl);
    if (nl <= WN) DK(block_narrow)(&V->s, &V->pp, sc, 1); /* one row (dk_velocity_one): WN lanes, not W */
    else DK(block)(&V->s, &V->pp, sc, 1);
    for (int l = 0; l < nl; l++) {
        const int64_t b = b0 + l;
        const real *qb = q + b * n;
        int finite = 1;
        for (int i = 0; i < n; i++) finite &= isfinite(qb[i]) != 0;
        real *vo = (real *)v->v + b * nv, *qn = v->q_next ? (real *)v->q_next + b * n : NULL;
        const int ok = DK(vel_row)(V, sc, l, qb, tgt + b * v->target_stride, qref ? qref + b * v->ref_stride : NULL,
                                   vo, qn, work, fixed, fr,
                                   v->com_target ? (const real *)v->com_target + b * v->com_stride : NULL);
        if (v->ok) v->ok[b] = (uint8_t)(ok && finite);
    }
}

static void DK(vel_read)(const dk_args *a, const dk_vel *v, DK(Vel) *V) {
    V->v = v;
    V->F = (int)v->n_frames;
    V->nv = V->s.nv;
    V->n = V->s.n;
    V->fend = v->frame_end;
    V->fcost = (const real *)v->frame_cost;
    V->fgain = (const real *)v->frame_gain;
    V->flm = (const real *)v->frame_lm;
    V->pcost = (const real *)v->posture_cost;
    V->plo = (const real *)v->pos_lo;
    V->phi = (const real *)v->pos_hi;
    V->vmax = (const real *)v->vmax;
    V->pgain = (real)v->posture_gain;
    V->plm = (real)v->posture_lm;
    V->lgain = (real)v->limit_gain;
    V->dt = (real)v->dt;
    V->damping = (real)v->damping;
    (void)a;
}

/* The call of dk_velocity for reals of this type; returns the number of non-finite entries of q, -1 when
 * memory ran out. */
static int64_t DK(velocity)(const dk_args *a, dk_vel *v) {
    DK(Vel) V;
    read_shape(a, &V.s);
    DK(vel_read)(a, v, &V);
    const int64_t B = v->batch, nblocks = (B + W - 1) / W;
    int nthreads = (int)v->nthreads;
    if (nthreads < 1 || B <= SERIAL_MAX) nthreads = 1;
    int64_t bad = 0;
    if (nthreads == 1 && v->work) { /* the kept work space: plans and space made by the first call */
        size_t so, to;
        DK(vel_keep_split)(&V.s, &so, &to);
        char *mem = (char *)v->work;
        DK(bind_params)(a, &V.s, &V.pp, mem);
        int32_t *ints = (int32_t *)(mem + so);
        DK(Scratch) sc;
        if (!v->ready) {
            Space tmp;
            if (space_read(&V.s, &tmp)) return -1;
            memcpy(ints, tmp.vq, sizeof(int32_t) * (size_t)(V.s.nv + 3 * V.s.n + 1));
            free(tmp.vq);
            DK(plan_params)(a, &V.s, &V.pp);
            DK(scratch_init)(&V.s, &V.pp, (real *)(mem + to), &sc);
            ints[V.s.nv + 3 * V.s.n] = tmp.nb;
            v->ready = 1;
        } else {
            DK(scratch_bind)(&V.s, (real *)(mem + to), &sc);
        }
        V.sp.n = V.s.n, V.sp.nv = V.s.nv, V.sp.nb = ints[V.s.nv + 3 * V.s.n];
        V.sp.vq = ints, V.sp.qs = ints + V.s.nv, V.sp.vs = V.sp.qs + V.s.n, V.sp.slot = V.sp.vs + V.s.n;
        for (int64_t blk = 0; blk < nblocks; blk++) DK(vel_block)(&V, &sc, mem + to, blk, &bad);
        return bad;
    }
    if (DK(read_params)(a, &V.s, &V.pp)) return -1;
    if (space_read(&V.s, &V.sp)) { free(V.pp.fix); return -1; }
    const size_t per = DK(vel_thread_bytes)(&V.s);
    size_t stride;
    char *all = (char *)DK(team_alloc)((per + sizeof(real) - 1) / sizeof(real), nthreads, &stride);
    if (!all) { free(V.sp.vq); free(V.pp.fix); return -1; }
    stride *= sizeof(real);
#pragma omp parallel num_threads(nthreads) if (nthreads > 1) reduction(+ : bad)
    {
        char *mine = all + stride * (size_t)thread_id();
        DK(Scratch) sc;
        DK(scratch_init)(&V.s, &V.pp, (real *)mine, &sc);
#pragma omp for schedule(dynamic, 4)
        for (int64_t blk = 0; blk < nblocks; blk++) DK(vel_block)(&V, &sc, mine, blk, &bad);
    }
    free(all);
    free(V.sp.vq);
    free(V.pp.fix);
    return bad;
}

#if DK_VEL_PASS == 2 /* after the second (float) pass: both types exist */
static int vel_ok(const dk_args *a, const dk_vel *v) {
    return DK_LAYOUT_OK(a, dk_args, DK_ABI_VERSION) && (a->real_bytes == 8 || a->real_bytes == 4) &&
           DK_LAYOUT_OK(v, dk_vel, DK_VEL_VERSION);
}

/* Bytes of the work space a serial call of dk_velocity may keep in v->work for the chain a. */
int64_t dk_velocity_work_bytes(const dk_args *a) {
    if (!DK_LAYOUT_OK(a, dk_args, DK_ABI_VERSION)) return DK_ABI_ERROR;
    return a->real_bytes == 8 ? DK_VEL_F64(velocity_work_bytes)(a) : DK_VEL_F32(velocity_work_bytes)(a);
}

/* One row (dk_velocity_one): base's constants with this call's q (nq), target (F x 16), q_ref (nq), v (nv),
 * q_next (nq, or NULL) and dt in a copy of base, so that calls from several threads are safe; the kept work
 * space is used by one call at a time (a call that finds it busy allocates its own). */
int64_t dk_velocity_one(const dk_args *a, dk_vel *base, const dk_watch *w, const void *q, const void *target,
                        const void *q_ref, void *v, void *q_next, double dt) {
    if (!vel_ok(a, base)) return DK_ABI_ERROR;
    if (w && !DK_LAYOUT_OK(w, dk_watch, DK_WATCH_VERSION)) return DK_ABI_ERROR;
    if (w && dk_unchanged(w) != 1) return DK_STALE;
    dk_vel c = *base;
    c.batch = 1, c.nthreads = 1, c.q = q, c.target = target, c.target_stride = 0, c.q_ref = q_ref;
    c.ref_stride = 0, c.v = v, c.q_next = q_next, c.dt = dt;
    if (!base->work || __atomic_exchange_n(&base->busy, 1, __ATOMIC_ACQUIRE)) {
        c.work = NULL;
        return a->real_bytes == 8 ? DK_VEL_F64(velocity)(a, &c) : DK_VEL_F32(velocity)(a, &c);
    }
    c.ready = base->ready;
    const int64_t r = a->real_bytes == 8 ? DK_VEL_F64(velocity)(a, &c) : DK_VEL_F32(velocity)(a, &c);
    base->ready = c.ready;
    __atomic_store_n(&base->busy, 0, __ATOMIC_RELEASE);
    return r;
}

/* The number of entries of x (n reals of real_bytes) that are NaN or infinite. */
static int64_t vel_nonfinite(const void *x, int64_t n, int64_t real_bytes) {
    int64_t bad = 0;
    if (real_bytes == 8)
        for (int64_t i = 0; i < n; i++) bad += !isfinite(((const double *)x)[i]);
    else
        for (int64_t i = 0; i < n; i++) bad += !isfinite(((const float *)x)[i]);
    return bad;
}

/* dk_velocity_one with its arguments in two blocks, so that a caller through ctypes converts two, not nine:
 * h = {dk_args *, dk_vel *, dk_watch *} (the problem's, fixed) and call = {q, target, q_ref, v, q_next as
 * 64-bit addresses (0: NULL), then dt as a double}, packed per call by the caller (an immutable buffer of
 * its own: calls from several threads never share it). Non-finite targets or q_ref (of a posture task):
 * their number of non-finite entries is returned and nothing is computed (the caller's checked path names
 * them). */
int64_t dk_velocity_step(const void *const *h, const void *call) {
    uint64_t p[5];
    double dt;
    memcpy(p, call, sizeof p);
    memcpy(&dt, (const char *)call + sizeof p, sizeof dt);
    const dk_args *a = (const dk_args *)h[0];
    const dk_vel *v = (const dk_vel *)h[1];
    if (!vel_ok(a, v)) return DK_ABI_ERROR;
    const int64_t bad = (p[1] ? vel_nonfinite((const void *)(uintptr_t)p[1], 16 * v->n_frames, a->real_bytes) : 0) +
                        (p[2] && v->posture_cost ? vel_nonfinite((const void *)(uintptr_t)p[2], a->n, a->real_bytes) : 0);
    if (bad) return bad;
    return dk_velocity_one((const dk_args *)h[0], (dk_vel *)h[1], (const dk_watch *)h[2], (const void *)(uintptr_t)p[0],
                           (const void *)(uintptr_t)p[1], (const void *)(uintptr_t)p[2], (void *)(uintptr_t)p[3],
                           (void *)(uintptr_t)p[4], dt);
}

/* One step of differential IK for the v->batch rows of v (see the top of this file) on the chain a, whose
 * packed constants are checked against w first (NULL: not checked; changed: DK_STALE, nothing computed).
 * Returns the number of non-finite entries of q (their rows get ok = 0), -1 when memory ran out,
 * DK_ABI_ERROR for a dk_args or dk_vel of another version or size. */
int64_t dk_velocity(const dk_args *a, dk_vel *v, const dk_watch *w) {
    if (!vel_ok(a, v)) return DK_ABI_ERROR;
    if (w && !DK_LAYOUT_OK(w, dk_watch, DK_WATCH_VERSION)) return DK_ABI_ERROR;
    if (w && dk_unchanged(w) != 1) return DK_STALE;
    return a->real_bytes == 8 ? DK_VEL_F64(velocity)(a, v) : DK_VEL_F32(velocity)(a, v);
}
#endif
