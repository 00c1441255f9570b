/* The chain product (2.50), the geometric Jacobian (3.30) and the IK solver's Levenberg-Marquardt
 * iteration, fused into one pass per configuration: the native twin of diffkin.kernels.tree,
 * diffkin.kernels.jacobian, diffkin.kernels.pose_error (rotation-vector error) and diffkin.kernels.dls for
 * CPU calls without autograd (diffkin/kernels/native.py loads it; tests/test_native.py checks it against
 * those modules).
 *
 *     F_j = F_parent(j) . Pre_j . M_j . Post_j,   end k:  F_ends[k] . E_k
 *     R:  M_j = Rot_z(m_j q[i_j] + b_j),   J_k[:, v_j] += m_j [z_j x (p_e - p_j); z_j]
 *     P:  M_j = Trans_z(m_j q[i_j] + b_j), J_k[:, v_j] += m_j [z_j; 0]
 *     S:  M_j = Rot(q[i_j .. i_j + 3] / |.|) (2.33), J_k[:, v_j + c] = [a_c x (p_e - p_j); a_c], c = x, y, z
 *
 * with z_j (a_c: its axis c), p_j the z axis and origin of F_parent . Pre_j . M_j: the elementary motions of
 * diffkin.kernels.configuration (DK_MOTIONS below; each frame carries the code of its motion), q in qpos
 * order (nq = n columns), the Jacobian in velocity order (nv columns; an S motion has 4 coordinates and 3
 * velocities, the angular velocity in its rotated frame, as MuJoCo's ball joints). A quaternion is
 * normalised first; one of norm ~0 is the identity (as diffkin._numerics.stable_normalize).
 *
 * Configurations are processed in blocks of W lanes; every loop over the lanes is branch-free so the
 * compiler vectorises it, and sin/cos are evaluated by a vectorisable Cody-Waite reduction and Cephes
 * polynomials (|x| >= 1e5 falls back to libm). Blocks are shared between threads with a dynamic schedule.
 * The float FK evaluates sin/cos in float (8 lanes to an AVX2 register), the LM iteration in double.
 *
 * The interface is one struct per entry point, each an X-macro list of its fields that native.py mirrors
 * field by field as a ctypes.Structure: dk_args (DK_ARGS_FIELDS: the chain's arrays, 3x4 row-major blocks
 * for the fixed transforms, and one FK call's inputs and outputs) for dk_fk and as the chain of every other
 * entry; dk_solve_args (DK_SOLVE_FIELDS, _native_solve.c's: the chain's address, the LM constants, the
 * solve's inputs and outputs) for dk_solve and dk_solve_one; dk_watch (DK_WATCH_FIELDS) for the cache checks; dk_collide
 * (DK_COLLIDE_FIELDS) for dk_collide_clear; dk_vel (_native_velocity.c); dk_plan (_native_plan.c: the planner's
 * RRT-Connect). Each struct starts with its own
 * version and its size: DK_LAYOUT exports dk_layout_<tag>() (version, sizeof, every field's offset) and
 * dk_names_<tag>() (the field names), which native.py checks at load for every struct, and every entry point
 * refuses a struct whose version or size is not this file's (DK_ABI_ERROR). A new solver option therefore
 * changes dk_solve_args only, never dk_args. The status codes and limits Python reads (DK_CONSTANTS) are
 * exported by dk_constants() / dk_constant_names() and checked against native.py's CONSTANTS at load.
 *
 * The file includes itself once per real type (DK_REAL): the first pass holds what is type-free.
 */
#ifndef DK_REAL

#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#ifdef _OPENMP
#include <omp.h>
#endif

#define W 16
#define WN 4 /* the lanes of DK(block_narrow) */
#define SERIAL_MAX 512 /* configurations below which no thread is started */
/* A cover's slack in units of eta (_native_plan.c, DK(plan_edge_cover)): clear of margin + 3 eta, a sample proves
 * its neighbours, one sub-step (at most 2 eta of travel) away; so margin + 3 eta is the largest threshold a
 * search decides at (diffkin.motion._reach.pairs_apart leaves out the self pairs proven that far apart) */
#define COVER_SLACK 3
#define DK_ABI_VERSION 4 /* dk_args: bump with every change of DK_ARGS_FIELDS (and native.py's ABI_VERSION) */
#define DK_SOLVE_VERSION 1 /* dk_solve_args: bump with every change of DK_SOLVE_FIELDS (native.SolveArgs) */
#define DK_WATCH_VERSION 1 /* dk_watch: bump with every change of DK_WATCH_FIELDS (native.WatchArgs) */
#define DK_COLLIDE_VERSION 2 /* dk_collide: bump with every change of DK_COLLIDE_FIELDS (native.Collide) */
#define DK_CLIP_VERSION 3 /* dk_clip: bump with every change of DK_CLIP_FIELDS (native.ClipArgs) */
#define DK_ABI_ERROR (-2) /* returned for a struct of another version or size */
#define DK_RANGE_ERROR (-3) /* dk_solve: an option beyond this file's limits (lib_ranks > MAX_RANKS) */
#define DK_STALE (-4) /* dk_fk_one: the watched constants changed since they were packed */
#define DK_NOT_RIGID (-5) /* dk_solve_one: the target is not a rigid transform (or not finite) */

/* The layout of a struct T of fields FIELDS (X(type, name, what) lists) and version VERSION, exported for
 * native.py's load-time check: dk_layout_<tag>(out, cap) writes out[0] = VERSION, out[1] = sizeof(T),
 * out[2] = the number of fields, out[3 + i] = the offset of field i (what fits in cap entries) and returns
 * the number of entries there are; dk_names_<tag>() the field names, in order, each followed by a comma. */
#define DK_NAME(type, name, what) #name ","
#define DK_OFFSET(type, name, what) (int64_t)((const char *)&probe->name - (const char *)probe),
#define DK_LAYOUT(tag, T, FIELDS, VERSION) \
    const char *dk_names_##tag(void) { return FIELDS(DK_NAME); } \
    int64_t dk_layout_##tag(int64_t *out, int64_t cap) { \
        static T probe_struct; \
        const T *probe = &probe_struct; \
        const int64_t offs[] = {FIELDS(DK_OFFSET)}; \
        const int64_t nf = (int64_t)(sizeof offs / sizeof offs[0]); \
        const int64_t head[3] = {VERSION, (int64_t)sizeof(T), nf}; \
        for (int64_t i = 0; i < 3 + nf && i < cap; i++) out[i] = i < 3 ? head[i] : offs[i - 3]; \
        return 3 + nf; \
    }
/* a struct pointer p of type T is not NULL and has T's version and size */
#define DK_LAYOUT_OK(p, T, VERSION) ((p) && (p)->version == (VERSION) && (p)->size == (int64_t)sizeof(T))

#define DK_ARGS_FIELDS(X) \
    X(int64_t, version, "DK_ABI_VERSION") \
    X(int64_t, size, "sizeof(dk_args)") \
    X(int64_t, real_bytes, "8 or 4") \
    X(int64_t, nthreads, "threads to use for large batches (at least 1)") \
    X(int64_t, J, "joint frames") \
    X(int64_t, K, "end links") \
    X(int64_t, n, "variables (columns of q: nq)") \
    X(int64_t, nv, "velocities (columns of the Jacobian: nv)") \
    X(int64_t, has_base, "base[] is not the identity") \
    X(const int32_t *, parent, "[J] parent frame, -1 the base") \
    X(const int32_t *, motion, "[J] the code of the frame's motion (DK_MOTIONS)") \
    X(const int32_t *, qidx, "[J] the (first) variable driving the frame") \
    X(const int32_t *, vidx, "[J] the (first) velocity of the frame: its Jacobian column") \
    X(const int32_t *, has_pre, "[J] pre[j] is not the identity") \
    X(const int32_t *, has_post, "[J] post[j] is not the identity") \
    X(const int32_t *, end_joint, "[K] the frame end link k hangs from, -1 the base") \
    X(const int32_t *, has_end, "[K] end[k] is not the identity") \
    X(const int32_t *, ancestor, "[K*J] joint j moves end link k") \
    X(const void *, mult, "[J] reals: q_j = mult_j q[qidx_j] + qoff_j") \
    X(const void *, qoff, "[J] reals") \
    X(const void *, pre, "[12J] reals") \
    X(const void *, post, "[12J] reals") \
    X(const void *, base, "[12] reals") \
    X(const void *, end, "[12K] reals") \
    X(int64_t, batch, "B") \
    X(const void *, q, "dk_fk: [B*n] reals in") \
    X(void *, T, "dk_fk: [B*K*16] reals out") \
    X(void *, jac, "dk_fk: [B*K*6*nv] reals out, or NULL")
/* X(letter, nq, nv, what): the elementary motions in code order (DK_MOTION_P = 0, ...), as
 * diffkin.kernels.configuration declares them (MOTION_NQ, MOTION_NV); native.py reads this table through
 * dk_motions() at load time, checks it against its own and packs each frame's code from it. */
#define DK_MOTIONS(X) \
    X(P, 1, 1, "translation along z") \
    X(R, 1, 1, "rotation about z") \
    X(S, 4, 3, "rotation by a quaternion (w, x, y, z), angular velocity in the rotated frame")

#define DK_CODE(letter, nq, nv, what) DK_MOTION_##letter,
enum { DK_MOTIONS(DK_CODE) DK_N_MOTIONS };
#undef DK_CODE

/* "letter nq nv," per motion, in code order. */
const char *dk_motions(void) {
#define DK_ROW(letter, nq, nv, what) #letter " " #nq " " #nv ","
    return DK_MOTIONS(DK_ROW);
#undef DK_ROW
}

#define DK_DECLARE(type, name, what) type name;
typedef struct dk_args { DK_ARGS_FIELDS(DK_DECLARE) } dk_args;

/* A byte snapshot of the tensors a chain's packed constants were made from (kernels/single.py): n regions,
 * region i at address ptr[i] of bytes[i] bytes, their bytes one after another in snap. A write that bumps no
 * version counter (p.data.add_(), a tensor shared with numpy) still changes the bytes. work (NULL, or
 * dk_fk_work_bytes of the one dk_args it serves) keeps dk_fk_one's plans and zeroed scratch between calls:
 * ready once the first call made them, busy while a call uses them. */
#define DK_WATCH_FIELDS(X) \
    X(int64_t, version, "DK_WATCH_VERSION") \
    X(int64_t, size, "sizeof(dk_watch)") \
    X(int64_t, n, "regions") \
    X(const int64_t *, ptr, "[n] addresses") \
    X(const int64_t *, bytes, "[n] sizes") \
    X(const uint8_t *, snap, "the regions' bytes one after another") \
    X(void *, work, "dk_fk_one's work space, or NULL") \
    X(int64_t, ready, "the work space holds the plans") \
    X(int64_t, busy, "a call uses the work space")
typedef struct dk_watch { DK_WATCH_FIELDS(DK_DECLARE) } dk_watch;

/* The arguments of dk_collide_clear (_native_collide.c); reals of real_bytes. */
#define DK_COLLIDE_FIELDS(X) \
    X(int64_t, version, "DK_COLLIDE_VERSION") \
    X(int64_t, size, "sizeof(dk_collide)") \
    X(int64_t, real_bytes, "8 or 4") \
    X(int64_t, N, "configurations") \
    X(int64_t, G, "capsules") \
    X(int64_t, P, "checked self pairs") \
    X(int64_t, Wr, "round world objects") \
    X(int64_t, H, "half-spaces") \
    X(int64_t, nthreads, "threads (at least 1)") \
    X(const void *, A, "[G*3*N] reals: capsule ends, component-major") \
    X(const void *, B, "[G*3*N] reals") \
    X(const void *, r, "[G] reals: radii") \
    X(const int64_t *, pi, "[P] first capsule of each pair") \
    X(const int64_t *, pj, "[P] second capsule") \
    X(const void *, wa, "[Wr*3] reals: round objects' segment ends") \
    X(const void *, wb, "[Wr*3] reals") \
    X(const void *, wr, "[Wr] reals: radii") \
    X(const void *, hs, "[H*4] reals: half-spaces n, offset") \
    X(const uint8_t *, skip_r, "[G*Wr] entries left out, or NULL") \
    X(const uint8_t *, skip_h, "[G*H] entries left out, or NULL") \
    X(double, margin, "") \
    X(double, slack, "") \
    X(uint8_t *, ok, "[N] in/out: cleared where some distance fails") \
    X(int64_t, Wb, "world boxes") \
    X(int64_t, Wy, "world cylinders") \
    X(int64_t, nw, "worlds (the object arrays carry nw leading rows)") \
    X(const int64_t *, wid, "[N] the world of each configuration, or NULL: world 0 for all") \
    X(const void *, bc, "[Wb*3] reals: box centres") \
    X(const void *, bR, "[Wb*9] reals: box rotations, row-major") \
    X(const void *, bh, "[Wb*3] reals: box half extents") \
    X(const void *, ya, "[Wy*3] reals: cylinders' flat faces' centres") \
    X(const void *, yb, "[Wy*3] reals") \
    X(const void *, yr, "[Wy] reals: cylinder radii") \
    X(const uint8_t *, skip_b, "[G*Wb] entries left out, or NULL") \
    X(const uint8_t *, skip_y, "[G*Wy] entries left out, or NULL") \
    X(const uint8_t *, point, "[G] capsule g is a sphere (its ends coincide); cylinders: only these")
typedef struct dk_collide { DK_COLLIDE_FIELDS(DK_DECLARE) } dk_collide;

/* The arguments of dk_clip_rows (_native_clip.c: the frame terms of the whole-clip retargeting problem);
 * reals of real_bytes, every array contiguous. */
#define DK_CLIP_FIELDS(X) \
    X(int64_t, version, "DK_CLIP_VERSION") \
    X(int64_t, size, "sizeof(dk_clip)") \
    X(int64_t, real_bytes, "8 or 4") \
    X(int64_t, nthreads, "threads (at least 1)") \
    X(int64_t, N, "frames of all clips (B T)") \
    X(int64_t, T, "frames per clip") \
    X(int64_t, nv, "velocities (Jacobian columns)") \
    X(int64_t, ends, "end links of the FK outputs") \
    X(int64_t, K, "keypoints") \
    X(int64_t, Ko, "orientation targets") \
    X(int64_t, P0, "sole points of the left foot") \
    X(int64_t, P1, "sole points of the right foot") \
    X(const int64_t *, kp, "[K] end link of each keypoint") \
    X(const void *, kp_w, "[K] reals: keypoint weights") \
    X(const void *, x, "[N*K*3] reals: keypoint targets") \
    X(const int64_t *, ko, "[Ko] end link of each orientation target") \
    X(const void *, ko_w, "[Ko] reals: orientation weights") \
    X(const void *, Rd, "[N*Ko*9] reals: target rotations, row-major") \
    X(const int64_t *, feet, "[2] end links of the left and right foot") \
    X(const void *, pts, "[(P0+P1)*3] reals: sole points in the foot frames") \
    X(const void *, rad, "[P0+P1] reals: their radii") \
    X(const uint8_t *, contact, "[N*2] foot in contact") \
    X(const uint8_t *, support, "[ends*nv] the columns each end link's Jacobian can be non-zero in, or NULL") \
    X(double, w_contact, "contact-height weight") \
    X(double, w_pen, "penetration weight") \
    X(double, w_flat, "flat-foot weight") \
    X(double, w_skate, "skating weight") \
    X(double, ground, "ground height") \
    X(const void *, Tf, "[N*ends*16] reals: end-link poses, or NULL: from fk") \
    X(const void *, J, "[N*ends*6*nv] reals: their geometric Jacobians, or NULL: from fk") \
    X(const dk_args *, fk, "the chain's FK with q the N frames' configurations, where Tf and J are NULL") \
    X(void *, cost, "[N] reals out: 1/2 |r|^2 of the frame's rows") \
    X(void *, D, "[N*nv*nv] reals out: J^T J") \
    X(void *, E, "[N*nv*nv] reals out: the skating rows' block (n, n - 1)") \
    X(void *, g, "[N*nv] reals out: J^T r") \
    X(void *, centre, "[N*4] reals out: the sole centres (x, y), left then right") \
    X(void *, centre_jac, "[N*4*nv] reals out: their Jacobian rows")
typedef struct dk_clip { DK_CLIP_FIELDS(DK_DECLARE) } dk_clip;

DK_LAYOUT(args, dk_args, DK_ARGS_FIELDS, DK_ABI_VERSION)
DK_LAYOUT(watch, dk_watch, DK_WATCH_FIELDS, DK_WATCH_VERSION)
DK_LAYOUT(collide, dk_collide, DK_COLLIDE_FIELDS, DK_COLLIDE_VERSION)
DK_LAYOUT(clip, dk_clip, DK_CLIP_FIELDS, DK_CLIP_VERSION)

static int thread_id(void) {
#ifdef _OPENMP
    return omp_get_thread_num();
#else
    return 0;
#endif
}

typedef struct {
    int J, K, n, nv, has_base;
    const int32_t *parent, *motion, *qidx, *vidx, *has_pre, *has_post, *end_joint, *has_end, *anc;
} Shape;

static void read_shape(const dk_args *a, Shape *s) {
    s->J = (int)a->J;
    s->K = (int)a->K;
    s->n = (int)a->n;
    s->nv = (int)a->nv;
    s->has_base = (int)a->has_base;
    s->parent = a->parent;
    s->motion = a->motion;
    s->qidx = a->qidx;
    s->vidx = a->vidx;
    s->has_pre = a->has_pre;
    s->has_post = a->has_post;
    s->end_joint = a->end_joint;
    s->has_end = a->has_end;
    s->anc = a->ancestor;
}

/* sin and cos of the first nw of W lanes of double, vectorisable (inlined: nw a constant at each call). */
static inline __attribute__((always_inline)) void sincos_lanes(const double *x, double *s, double *c,
                                                               const int nw) {
    const double two_over_pi = 0.63661977236758134308;
    const double P1 = 1.57079632673412561417e+00, P2 = 6.07710050630396597660e-11,
                 P3 = 2.02226624871116645580e-21;
    int big = 0;
    for (int l = 0; l < nw; l++) big |= !(fabs(x[l]) < 1e5);
    if (big) { /* far from the origin (or not finite): libm's full reduction */
        for (int l = 0; l < nw; l++) { s[l] = sin(x[l]); c[l] = cos(x[l]); }
        return;
    }
    /* k = round(x 2/pi) by the 1.5 2^52 shift, whose low mantissa bits are then k mod 4 (the quadrant): no
     * nearbyint/floor and no double -> int64 conversion, which AVX2 lacks and which kept the loop scalar */
    const double shift = 6755399441055744.0;
#pragma omp simd
    for (int l = 0; l < nw; l++) {
        const double t = x[l] * two_over_pi + shift, k = t - shift;
        uint64_t q;
        memcpy(&q, &t, sizeof q);
        double r = ((x[l] - k * P1) - k * P2) - k * P3;
        double z = r * r;
        double sp = r + r * z * (-1.66666666666666307295e-1 + z * (8.33333333332211858878e-3 +
                    z * (-1.98412698295895385996e-4 + z * (2.75573136213857245213e-6 +
                    z * (-2.50507477628578072866e-8 + z * 1.58962301576546568060e-10)))));
        double cp = 1.0 - 0.5 * z + z * z * (4.16666666666665929218e-2 + z * (-1.38888888888730564116e-3 +
                    z * (2.48015872888517045348e-5 + z * (-2.75573141792967388112e-7 +
                    z * (2.08757008419747316778e-9 + z * -1.13585365213876817300e-11)))));
        const double sv = (q & 1) ? cp : sp, cv = (q & 1) ? sp : cp;
        s[l] = (q & 2) ? -sv : sv;
        c[l] = ((q + 1) & 2) ? -cv : cv;
    }
}

/* sin and cos of W lanes of float, vectorisable, 8 lanes to an AVX2 register where the double version has
 * 4: the same reduction in float (pi/2 in three parts, k x P1 exact for |k| < 2^16) and Cephes' sinf/cosf
 * polynomials on [-pi/4, pi/4] (about 1 ulp); |x| >= 1e4 (or not finite) takes the double version. */
static inline __attribute__((always_inline)) void sincos_lanes_f32(const float *x, float *s, float *c,
                                                                   const int nw) {
    int big = 0;
    for (int l = 0; l < nw; l++) big |= !(fabsf(x[l]) < 1e4f);
    if (big) {
        double xd[W], sd[W], cd[W];
        for (int l = 0; l < nw; l++) xd[l] = x[l];
        sincos_lanes(xd, sd, cd, nw);
        for (int l = 0; l < nw; l++) { s[l] = (float)sd[l]; c[l] = (float)cd[l]; }
        return;
    }
    const float shift = 12582912.0f; /* 1.5 2^23: round to an integer, k mod 4 in the low mantissa bits */
#pragma omp simd
    for (int l = 0; l < nw; l++) {
        const float t = x[l] * 0.636619772f + shift, k = t - shift;
        uint32_t q;
        memcpy(&q, &t, sizeof q);
        const float r = ((x[l] - k * 1.5703125f) - k * 4.837512969970703125e-4f) - k * 7.54978995489188216e-8f;
        const float z = r * r;
        const float sp = r + r * z * ((-1.9515295891e-4f * z + 8.3321608736e-3f) * z - 1.6666654611e-1f);
        const float cp = 1.0f - 0.5f * z + z * z * ((2.443315711809948e-5f * z - 1.388731625493765e-3f) * z +
                                                    4.166664568298827e-2f);
        const float sv = (q & 1) ? cp : sp, cv = (q & 1) ? sp : cp;
        s[l] = (q & 2) ? -sv : sv;
        c[l] = ((q + 1) & 2) ? -cv : cv;
    }
}

enum { MOVE_NONE, MOVE_TURN, MOVE_SLIDE }; /* the motion of a joint in DK(rows) */

#if defined(__AVX2__)
#include <immintrin.h>
/* Transposes of one register tile, for DK(store_lanes): rows of src (ss apart) become rows of dst (ds apart). */
static inline void transpose_f32(const float *src, size_t ss, float *dst, int64_t ds) {
    __m256 r[8], t[8], u[8];
    for (int i = 0; i < 8; i++) r[i] = _mm256_loadu_ps(src + i * ss);
    for (int i = 0; i < 4; i++) {
        t[2 * i] = _mm256_unpacklo_ps(r[2 * i], r[2 * i + 1]);
        t[2 * i + 1] = _mm256_unpackhi_ps(r[2 * i], r[2 * i + 1]);
    }
    for (int h = 0; h < 2; h++) /* rows 0-3, 4-7 */
        for (int i = 0; i < 2; i++) {
            u[4 * h + 2 * i] = _mm256_shuffle_ps(t[4 * h + i], t[4 * h + i + 2], _MM_SHUFFLE(1, 0, 1, 0));
            u[4 * h + 2 * i + 1] = _mm256_shuffle_ps(t[4 * h + i], t[4 * h + i + 2], _MM_SHUFFLE(3, 2, 3, 2));
        }
    for (int i = 0; i < 4; i++) {
        _mm256_storeu_ps(dst + i * ds, _mm256_permute2f128_ps(u[i], u[i + 4], 0x20));
        _mm256_storeu_ps(dst + (i + 4) * ds, _mm256_permute2f128_ps(u[i], u[i + 4], 0x31));
    }
}

static inline void transpose_f64(const double *src, size_t ss, double *dst, int64_t ds) {
    const __m256d r0 = _mm256_loadu_pd(src), r1 = _mm256_loadu_pd(src + ss);
    const __m256d r2 = _mm256_loadu_pd(src + 2 * ss), r3 = _mm256_loadu_pd(src + 3 * ss);
    const __m256d t0 = _mm256_unpacklo_pd(r0, r1), t1 = _mm256_unpackhi_pd(r0, r1);
    const __m256d t2 = _mm256_unpacklo_pd(r2, r3), t3 = _mm256_unpackhi_pd(r2, r3);
    _mm256_storeu_pd(dst, _mm256_permute2f128_pd(t0, t2, 0x20));
    _mm256_storeu_pd(dst + ds, _mm256_permute2f128_pd(t1, t3, 0x20));
    _mm256_storeu_pd(dst + 2 * ds, _mm256_permute2f128_pd(t0, t2, 0x31));
    _mm256_storeu_pd(dst + 3 * ds, _mm256_permute2f128_pd(t1, t3, 0x31));
}
#endif

#define DK_REAL double
#define DK(name) name##_f64
#define DK_TINY 2.2250738585072014e-308
#define DK_MAX 1.7976931348623157e308
#define DK_TILE 4
#define DK_TRANSPOSE transpose_f64
#define DK_SINCOS sincos_lanes
#define DK_QSMALL 1.4901161193847656e-11 /* sqrt(DBL_EPSILON) 1e-3 */
#include __FILE__
#undef DK_REAL
#undef DK
#undef DK_TINY
#undef DK_MAX
#undef DK_TILE
#undef DK_TRANSPOSE
#undef DK_SINCOS
#undef DK_QSMALL

#define DK_REAL float
#define DK(name) name##_f32
#define DK_TINY 1.17549435e-38f
#define DK_MAX 3.40282347e38f
#define DK_TILE 8
#define DK_TRANSPOSE transpose_f32
#define DK_SINCOS sincos_lanes_f32
#define DK_QSMALL 3.4526698300124393e-07f /* sqrt(FLT_EPSILON) 1e-3 */
#include __FILE__

static int abi_ok(const dk_args *a) {
    return DK_LAYOUT_OK(a, dk_args, DK_ABI_VERSION) && (a->real_bytes == 8 || a->real_bytes == 4);
}

static int watch_ok(const dk_watch *w) { return DK_LAYOUT_OK(w, dk_watch, DK_WATCH_VERSION); }

static int solve_ok(const dk_solve_args *o) {
    return DK_LAYOUT_OK(o, dk_solve_args, DK_SOLVE_VERSION) && abi_ok(o->chain);
}

/* X(name, what): the status codes and limits the Python side reads, exported by dk_constants() and
 * dk_constant_names() (as dk_layout_* / dk_names_*) and checked at load against native.py's CONSTANTS. */
#define DK_CONSTANTS(X) \
    X(DK_ABI_ERROR, "a struct of another version or size") \
    X(DK_RANGE_ERROR, "an option beyond this file's limits") \
    X(DK_STALE, "the watched constants changed") \
    X(DK_NOT_RIGID, "the target is not a rigid transform") \
    X(W, "lanes of a block") \
    X(CHUNK, "targets per chunk of the solve") \
    X(SERIAL_MAX, "configurations below which no thread is started") \
    X(MAX_RANKS, "library ranks a target may ask for") \
    X(MAX_ENDS, "end links the nearest-pose search takes") \
    X(COVER_SLACK, "a cover's slack in units of the resolution")

const char *dk_constant_names(void) {
#define DK_CNAME(name, what) #name ","
    return DK_CONSTANTS(DK_CNAME);
#undef DK_CNAME
}

/* out[i] = the value of constant i (what fits in cap entries); returns the number of constants. */
int64_t dk_constants(int64_t *out, int64_t cap) {
#define DK_CVALUE(name, what) (int64_t)(name),
    const int64_t values[] = {DK_CONSTANTS(DK_CVALUE)};
#undef DK_CVALUE
    const int64_t n = (int64_t)(sizeof values / sizeof values[0]);
    for (int64_t i = 0; i < n && i < cap; i++) out[i] = values[i];
    return n;
}

/* T (B, K, 4, 4) and, when jac is not NULL, J (B, K, 6, n) of q (B, n); returns the number of non-finite
 * entries of q (their outputs are not meaningful), -1 when memory ran out, DK_ABI_ERROR for a struct of
 * another layout. */
int64_t dk_fk(const dk_args *a) {
    if (!abi_ok(a)) return DK_ABI_ERROR;
    return a->real_bytes == 8 ? dk_fk_f64(a) : dk_fk_f32(a);
}

/* 1 when every region of w still holds its snapshot, else 0; DK_ABI_ERROR for a dk_watch of another
 * version or size. */
int64_t dk_unchanged(const dk_watch *w) {
    if (!watch_ok(w)) return DK_ABI_ERROR;
    const uint8_t *s = w->snap;
    for (int64_t i = 0; i < w->n; s += w->bytes[i], i++)
        if (w->bytes[i] && memcmp((const void *)(intptr_t)w->ptr[i], s, (size_t)w->bytes[i])) return 0;
    return 1;
}

/* Bytes of the work space dk_fk_one keeps in a dk_watch for calls of a. */
int64_t dk_fk_work_bytes(const dk_args *a) {
    if (!abi_ok(a)) return DK_ABI_ERROR;
    return a->real_bytes == 8 ? dk_fk_work_bytes_f64(a) : dk_fk_work_bytes_f32(a);
}

/* dk_fk of one configuration q (n) into T (K, 4, 4) and jac (K, 6, nv) or NULL, with base's constants,
 * when the tensors they were packed from are unchanged (dk_unchanged(w)); else DK_STALE, nothing computed.
 * One foreign call per lean single call (kernels/single.py): base is never written (calls from several
 * threads are safe); the plans and scratch are w's work space, made by the first call (a call that finds
 * it busy makes its own). */
int64_t dk_fk_one(const dk_args *base, dk_watch *w, const void *q, void *T, void *jac) {
    if (!abi_ok(base) || !watch_ok(w)) return DK_ABI_ERROR;
    if (dk_unchanged(w) != 1) return DK_STALE;
    dk_args a = *base;
    a.batch = 1;
    a.nthreads = 1;
    a.q = q;
    a.T = T;
    a.jac = jac;
    if (!w->work || __atomic_exchange_n(&w->busy, 1, __ATOMIC_ACQUIRE)) return dk_fk(&a);
    const int64_t bad = a.real_bytes == 8 ? dk_fk_work_f64(&a, w) : dk_fk_work_f32(&a, w);
    __atomic_store_n(&w->busy, 0, __ATOMIC_RELEASE);
    return bad;
}

/* The whole IK solve of dk_solve_f64 / dk_solve_f32 (_native_solve.c) with the arguments o on the chain
 * o->chain; returns 0, -1 when memory ran out, DK_RANGE_ERROR for lib_ranks > MAX_RANKS (nothing solved),
 * DK_ABI_ERROR for a dk_solve_args or dk_args of another version or size. */
int64_t dk_solve(const dk_solve_args *o) {
    if (!solve_ok(o)) return DK_ABI_ERROR;
    return o->chain->real_bytes == 8 ? dk_solve_f64(o->chain, o) : dk_solve_f32(o->chain, o);
}

/* The lean one-target ik.solve in one foreign call (ik/_native_solve.py solve_one): the watched constants
 * unchanged (else DK_STALE), the target T (4 x 4 row-major reals) rigid (else DK_NOT_RIGID), then dk_solve of
 * tmpl (filled one-target arguments and their chain, never written) with T, the pool drawn from `seed` (>= 0:
 * torch's CPU stream of manual_seed(seed), pool_size uniforms at most, drawn as needed) or read from `pool`
 * (seed < 0), into the outputs q (n reals), ok (1 byte), pe, oe (1 real each), its, seeds (1 int64 each).
 * Returns 0, DK_STALE, DK_NOT_RIGID, -1 when memory ran out, DK_RANGE_ERROR, DK_ABI_ERROR. */
int64_t dk_solve_one(const dk_solve_args *tmpl, const dk_watch *w, const void *T, int64_t seed,
                     const void *pool, int64_t pool_size, void *q, void *ok, void *pe, void *oe, void *its,
                     void *seeds) {
    if (!solve_ok(tmpl) || !watch_ok(w)) return DK_ABI_ERROR;
    if (dk_unchanged(w) != 1) return DK_STALE;
    const dk_args *a = tmpl->chain;
    return a->real_bytes == 8
        ? solve_one_f64(a, tmpl, (const double *)T, seed, pool, pool_size, q, ok, pe, oe, its, seeds)
        : solve_one_f32(a, tmpl, (const float *)T, seed, pool, pool_size, q, ok, pe, oe, its, seeds);
}

/* Clear ok[n] where configuration n has a checked capsule distance with d - margin < slack (see
 * _native_collide.c); returns 0, DK_ABI_ERROR for a struct of another version or size or a real size other
 * than 8 or 4. */
int64_t dk_collide_clear(const dk_collide *c) {
    if (!DK_LAYOUT_OK(c, dk_collide, DK_COLLIDE_VERSION)) return DK_ABI_ERROR;
    if (c->real_bytes == 8) dk_collide_f64(c);
    else if (c->real_bytes == 4) dk_collide_f32(c);
    else return DK_ABI_ERROR;
    return 0;
}

/* The block-banded SPD solve H x = g of batch systems (_native_banded.c; reals of real_bytes 8 or 4; F one
 * band for all systems where f_shared; shift: NULL or one real per system added to its diagonal). Returns
 * 0, -1 when the work space cannot be allocated, DK_ABI_ERROR for another real size. */
int64_t dk_banded_solve(const void *D, const void *E, const void *F, int64_t f_shared, const void *g,
                        const void *shift, void *x, int64_t batch, int64_t T, int64_t n, int64_t real_bytes,
                        int64_t nthreads) {
    if (real_bytes == 8)
        return banded_solve_f64((const double *)D, (const double *)E, (const double *)F, f_shared,
                                (const double *)g, (const double *)shift, (double *)x, batch, T, n, nthreads);
    if (real_bytes == 4)
        return banded_solve_f32((const float *)D, (const float *)E, (const float *)F, f_shared,
                                (const float *)g, (const float *)shift, (float *)x, batch, T, n, nthreads);
    return DK_ABI_ERROR;
}

/* The fine samples of motion._spline_clear (_native_spline.c, spline_fine; reals of real_bytes 8 or 4): in: u
 * (F + 1), knots (B, N), c0..c3 (B, N - 1, n), end (B, n), lo, hi, reach (n); cum (B, F + 1), inside (B) out,
 * work (B, 2 n). Returns 0, DK_ABI_ERROR for another real size. */
int64_t dk_spline_fine(const void *const *in, void *cum, void *inside, void *work, int64_t F, int64_t B,
                       int64_t N, int64_t n, int64_t real_bytes, int64_t nthreads) {
    if (real_bytes == 8) {
        const double *const *a = (const double *const *)in;
        spline_fine_f64(a[0], F, a[1], a[2], a[3], a[4], a[5], a[6], a[7], a[8], a[9], B, N, n, (double *)cum,
                        (double *)inside, (double *)work, nthreads);
        return 0;
    }
    if (real_bytes == 4) {
        const float *const *a = (const float *const *)in;
        spline_fine_f32(a[0], F, a[1], a[2], a[3], a[4], a[5], a[6], a[7], a[8], a[9], B, N, n, (float *)cum,
                        (float *)inside, (float *)work, nthreads);
        return 0;
    }
    return DK_ABI_ERROR;
}

/* The check points of motion._spline_clear (_native_spline.c, spline_marks): in: u (F + 1), cum (B, F + 1),
 * step (B), knots (B, N), c0..c3 (B, N - 1, n), end (B, n); count, first (B) int64; q (Σ (count + 1), n) out.
 * Returns 0, DK_ABI_ERROR for another real size. */
int64_t dk_spline_marks(const void *const *in, const int64_t *count, const int64_t *first, void *q, int64_t F,
                        int64_t B, int64_t N, int64_t n, int64_t real_bytes, int64_t nthreads) {
    if (real_bytes == 8) {
        const double *const *a = (const double *const *)in;
        spline_marks_f64(a[0], F, a[1], a[2], count, first, a[3], a[4], a[5], a[6], a[7], a[8], B, N, n,
                         (double *)q, nthreads);
        return 0;
    }
    if (real_bytes == 4) {
        const float *const *a = (const float *const *)in;
        spline_marks_f32(a[0], F, a[1], a[2], count, first, a[3], a[4], a[5], a[6], a[7], a[8], B, N, n,
                         (float *)q, nthreads);
        return 0;
    }
    return DK_ABI_ERROR;
}

/* q, q̇, q̈ of timed paths at the times in[0] (R, T) (_native_topp.c, topp_sample; reals of real_bytes 8 or 4):
 * rows (R, T) the path of each sample, or NULL (row r: path r). Returns 0, DK_ABI_ERROR for another real size. */
int64_t dk_topp_sample(const void *const *in, const int64_t *rows, void *q, void *qd, void *qdd, int64_t R,
                       int64_t T, int64_t M, int64_t N, int64_t n, int64_t real_bytes, int64_t nthreads) {
    if (real_bytes == 8)
        return topp_sample_f64((const double *const *)in, rows, (double *)q, (double *)qd, (double *)qdd, R, T, M,
                               N, n, nthreads);
    if (real_bytes == 4)
        return topp_sample_f32((const float *const *)in, rows, (float *)q, (float *)qd, (float *)qdd, R, T, M, N,
                               n, nthreads);
    return DK_ABI_ERROR;
}

/* The path's q', q'' at time_optimal's grid (_native_topp.c, topp_slopes; reals of real_bytes 8 or 4): in = (s
 * (B, N), c0..c3 (B, N - 1, n), grid (B, M)), kseg (B, M); P1, P2 (B, M, n), Q1, Q2 (B, M - 1, n) out. Returns
 * 0, DK_ABI_ERROR for another real size. */
int64_t dk_topp_slopes(const void *const *in, const int64_t *kseg, void *P1, void *P2, void *Q1, void *Q2,
                       int64_t B, int64_t M, int64_t N, int64_t n, int64_t real_bytes, int64_t nthreads) {
    if (real_bytes == 8)
        return topp_slopes_f64((const double *const *)in, kseg, (double *)P1, (double *)P2, (double *)Q1,
                               (double *)Q2, B, M, N, n, nthreads);
    if (real_bytes == 4)
        return topp_slopes_f32((const float *const *)in, kseg, (float *)P1, (float *)P2, (float *)Q1, (float *)Q2,
                               B, M, N, n, nthreads);
    return DK_ABI_ERROR;
}

/* TOPP-RA from the path's derivatives at the grid (_native_topp.c, topp_grid; reals of real_bytes 8 or 4): in
 * P1, P2 (B, M, n), Q1, Q2 (B, M - 1, n), amax, vmax (B, n), delta (B, M - 1), stops (B, M); x (B, M) out.
 * Returns 0, -1 when the work space cannot be allocated, DK_ABI_ERROR for another real size. */
int64_t dk_topp_grid(const void *const *in, void *x, int64_t B, int64_t M, int64_t n, double big,
                     int64_t real_bytes, int64_t nthreads) {
    if (real_bytes == 8) {
        const double *const *a = (const double *const *)in;
        return topp_grid_f64(a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7], (double *)x, B, M, n, big, nthreads);
    }
    if (real_bytes == 4) {
        const float *const *a = (const float *const *)in;
        return topp_grid_f32(a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7], (float *)x, B, M, n, (float)big,
                             nthreads);
    }
    return DK_ABI_ERROR;
}

/* The dense limit check of time_optimal (_native_topp.c, topp_peaks; reals of real_bytes 8 or 4): the peaks
 * (B, nlim) of B timed paths at the sample times in[0] (B, T) (in: the arrays listed there; top (B, nlim, n)
 * work). Returns 0,
 * DK_ABI_ERROR for another real size or nlim outside 2..3. */
int64_t dk_topp_peaks(const void *const *in, void *top, void *peak, int64_t B, int64_t T, int64_t M, int64_t N, int64_t n,
                      int64_t nlim, int64_t real_bytes, int64_t nthreads) {
    if (nlim < 2 || nlim > 3) return DK_ABI_ERROR;
    if (real_bytes == 8)
        return topp_peaks_f64((const double *const *)in, (double *)top, (double *)peak, B, T, M, N, n, nlim, nthreads);
    if (real_bytes == 4)
        return topp_peaks_f32((const float *const *)in, (float *)top, (float *)peak, B, T, M, N, n, nlim, nthreads);
    return DK_ABI_ERROR;
}

/* The joint terms of the whole-clip retargeting problem (_native_clip.c, clip_joint; reals of real_bytes 8 or
 * 4): in = (q, q_ref, lo, hi, vstep or NULL, w), idx = (sq, sv, bq, bv), added to cost, D, E, g. Returns 0,
 * -1 when the work space cannot be allocated, DK_ABI_ERROR for another real size. */
int64_t dk_clip_joint(const void *const *in, const int64_t *const *idx, void *cost, void *D, void *E, void *g,
                      int64_t B, int64_t T, int64_t nq, int64_t nv, int64_t ns, int64_t nb, int64_t real_bytes,
                      int64_t nthreads) {
    if (real_bytes == 8) {
        const double *const *a = (const double *const *)in;
        return clip_joint_f64(a[0], a[1], idx, ns, nb, a[2], a[3], a[4], B, T, nq, nv, a[5], (double *)cost,
                              (double *)D, (double *)E, (double *)g, nthreads);
    }
    if (real_bytes == 4) {
        const float *const *a = (const float *const *)in;
        return clip_joint_f32(a[0], a[1], idx, ns, nb, a[2], a[3], a[4], B, T, nq, nv, a[5], (float *)cost,
                              (float *)D, (float *)E, (float *)g, nthreads);
    }
    return DK_ABI_ERROR;
}

/* The whole-clip step q ⊕ step, projected (_native_clip.c, clip_step; reals of real_bytes 8 or 4): in = (q, step,
 * qlo, qhi, lo, hi, vstep or NULL), idx = (sq, sv, bq, bv), into out. Returns 0, DK_ABI_ERROR for another real
 * size. */
int64_t dk_clip_step(const void *const *in, const int64_t *const *idx, void *out, int64_t B, int64_t T, int64_t nq,
                     int64_t nv, int64_t ns, int64_t nb, int64_t real_bytes, int64_t nthreads) {
    if (real_bytes == 8) {
        const double *const *a = (const double *const *)in;
        return clip_step_f64(a[0], a[1], idx, ns, nb, a[2], a[3], a[4], a[5], a[6], B, T, nq, nv, (double *)out,
                             nthreads);
    }
    if (real_bytes == 4) {
        const float *const *a = (const float *const *)in;
        return clip_step_f32(a[0], a[1], idx, ns, nb, a[2], a[3], a[4], a[5], a[6], B, T, nq, nv, (float *)out,
                             nthreads);
    }
    return DK_ABI_ERROR;
}

/* The frame terms of the whole-clip retargeting problem (_native_clip.c) into c's outputs; returns 0, -1
 * when the work space cannot be allocated, DK_ABI_ERROR for a struct of another version or size or a real
 * size other than 8 or 4. */
int64_t dk_clip_rows(const dk_clip *c) {
    if (!DK_LAYOUT_OK(c, dk_clip, DK_CLIP_VERSION)) return DK_ABI_ERROR;
    if ((c->Tf == NULL || c->J == NULL) &&
        (c->fk == NULL || !abi_ok(c->fk) || c->fk->q == NULL || c->fk->batch < c->N))
        return DK_ABI_ERROR;
    if (c->real_bytes == 8) return clip_rows_f64(c);
    if (c->real_bytes == 4) return clip_rows_f32(c);
    return DK_ABI_ERROR;
}

#else /* ------------------------------------------------------------------- one pass per real type */

#define real DK_REAL

typedef struct { /* a constant 3x4 transform A (row-major; last row 0 0 0 1) as the lanes apply it: P . A */
    int perm;   /* every rotation column c has at most one non-zero, a[4 col[c] + c]: one product */
    int col[3];
    real a[12];
} DK(Fix);

typedef struct {
    const real *mult, *qoff, *base;
    DK(Fix) *fix; /* Pre_j (j < J), Post_j (J + j), E_k (2J + k); NULL arrays are the identity */
    uint8_t *first; /* [K*J] joint j is the first in the loop to reach its column of end k's Jacobian */
} DK(Params);

typedef struct { /* per-thread work space, all lane-major (W lanes innermost) */
    real *F, *A, *ends, *Jb, *qlanes, *basef;
} DK(Scratch);

static void DK(plan_fix)(const real *A, DK(Fix) *f) {
    static const real eye[12] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0};
    memcpy(f->a, A ? A : eye, sizeof f->a);
    f->perm = 1;
    for (int c = 0; c < 3; c++) {
        int nz = 0;
        f->col[c] = 0;
        for (int k = 0; k < 3; k++)
            if (f->a[4 * k + c] != 0) { nz++; f->col[c] = k; }
        f->perm &= nz <= 1;
    }
}

/* Bytes of a call's plans: 2J + K of them, then first[] and its seen[] (DK(bind_params)). */
static size_t DK(params_bytes)(const Shape *s) {
    return sizeof(DK(Fix)) * (size_t)(2 * s->J + s->K + 1) + (size_t)(s->K * s->J + s->nv + 1);
}

/* pp's pointers: the constants of a, the plans in mem (DK(params_bytes)); DK(plan_params) fills them. */
static void DK(bind_params)(const dk_args *a, const Shape *s, DK(Params) *pp, void *mem) {
    pp->mult = (const real *)a->mult;
    pp->qoff = (const real *)a->qoff;
    pp->base = (const real *)a->base;
    pp->fix = (DK(Fix) *)mem;
    pp->first = (uint8_t *)(pp->fix + (2 * s->J + s->K + 1));
}

static void DK(plan_params)(const dk_args *a, const Shape *s, DK(Params) *pp) {
    const real *pre = (const real *)a->pre, *post = (const real *)a->post, *end = (const real *)a->end;
    uint8_t *seen = pp->first + s->K * s->J;
    for (int k = 0; k < s->K; k++) {
        memset(seen, 0, (size_t)s->nv);
        for (int j = 0; j < s->J; j++) { /* an S frame's three columns are its own (no mimic coupling) */
            const int hit = s->anc[k * s->J + j];
            pp->first[k * s->J + j] = (uint8_t)(hit && !seen[s->vidx[j]]);
            seen[s->vidx[j]] |= (uint8_t)hit;
        }
    }
    for (int j = 0; j < s->J; j++) {
        DK(plan_fix)(s->has_pre[j] ? pre + 12 * j : NULL, pp->fix + j);
        DK(plan_fix)(s->has_post[j] ? post + 12 * j : NULL, pp->fix + s->J + j);
    }
    for (int k = 0; k < s->K; k++) DK(plan_fix)(s->has_end[k] ? end + 12 * k : NULL, pp->fix + 2 * s->J + k);
}

/* The parameters of a call; pp->fix is allocated (2J + K plans, then first[]), the caller frees it. */
static int DK(read_params)(const dk_args *a, const Shape *s, DK(Params) *pp) {
    void *mem = malloc(DK(params_bytes)(s));
    if (!mem) return -1;
    DK(bind_params)(a, s, pp, mem);
    DK(plan_params)(a, s, pp);
    return 0;
}

static size_t DK(scratch_size)(const Shape *s) {
    const size_t J = s->J, K = s->K, n = s->n, nv = s->nv;
    return sizeof(real) * W * (J * 12 + J * 12 + K * 12 + K * 6 * nv + n + 12);
}

static void DK(scratch_bind)(const Shape *s, real *buf, DK(Scratch) *sc) {
    const size_t J = s->J, K = s->K, n = s->n, nv = s->nv;
    sc->F = buf;
    sc->A = sc->F + J * 12 * W;
    sc->ends = sc->A + J * 12 * W;
    sc->Jb = sc->ends + K * 12 * W;
    sc->qlanes = sc->Jb + K * 6 * nv * W;
    sc->basef = sc->qlanes + n * W;
}

static void DK(scratch_init)(const Shape *s, const DK(Params) *pp, real *buf, DK(Scratch) *sc) {
    const size_t K = s->K, nv = s->nv;
    DK(scratch_bind)(s, buf, sc);
    memset(sc->Jb, 0, sizeof(real) * K * 6 * nv * W); /* columns no joint reaches stay 0 (DK(column)) */
    for (int e = 0; e < 12; e++)
        for (int l = 0; l < W; l++)
            sc->basef[e * W + l] = s->has_base ? pp->base[e] : (real)((e % 5) == 0); /* identity: 0, 5, 10 */
}

/* out = P . A . M for frames P (12 x W lanes), a constant A (f) and the joint motion M: a turn about z by
 * (cs, sn) per lane, a slide along z by cs per lane, or none. One pass over the lanes per row: the
 * product and the motion never leave the registers. perm and move are constants where this is inlined. */
static inline __attribute__((always_inline)) void DK(rows)(const real *restrict P, const DK(Fix) *f,
                                                           const int perm, const int move,
                                                           const real *restrict cs,
                                                           const real *restrict sn, real *restrict out,
                                                           const int nw) {
    const real *a = f->a;
    const real a0 = a[0], a1 = a[1], a2 = a[2], a3 = a[3], a4 = a[4], a5 = a[5], a6 = a[6], a7 = a[7];
    const real a8 = a[8], a9 = a[9], a10 = a[10], a11 = a[11];
    const real sx = a[4 * f->col[0]], sy = a[4 * f->col[1] + 1], sz = a[4 * f->col[2] + 2];
    for (int r = 0; r < 3; r++) {
        const real *restrict P0 = P + 4 * r * W, *restrict P1 = P0 + W, *restrict P2 = P1 + W;
        const real *restrict Pp = P2 + W;
        const real *restrict Cx = P0 + f->col[0] * W, *restrict Cy = P0 + f->col[1] * W;
        const real *restrict Cz = P0 + f->col[2] * W;
        real *restrict X = out + 4 * r * W, *restrict Y = X + W, *restrict Z = Y + W, *restrict Q = Z + W;
#pragma omp simd
        for (int l = 0; l < nw; l++) {
            real x, y, z;
            if (perm) {
                x = Cx[l] * sx;
                y = Cy[l] * sy;
                z = Cz[l] * sz;
            } else {
                x = P0[l] * a0 + P1[l] * a4 + P2[l] * a8;
                y = P0[l] * a1 + P1[l] * a5 + P2[l] * a9;
                z = P0[l] * a2 + P1[l] * a6 + P2[l] * a10;
            }
            const real p = Pp[l] + P0[l] * a3 + P1[l] * a7 + P2[l] * a11;
            if (move == MOVE_TURN) {
                const real c = cs[l], sv = sn[l];
                X[l] = c * x + sv * y;
                Y[l] = c * y - sv * x;
            } else {
                X[l] = x;
                Y[l] = y;
            }
            Z[l] = z;
            Q[l] = move == MOVE_SLIDE ? p + cs[l] * z : p;
        }
    }
}

static inline __attribute__((always_inline)) void DK(apply)(const real *P, const DK(Fix) *f, int move,
                                                            const real *cs, const real *sn, real *out,
                                                            const int nw) {
    if (f->perm) {
        if (move == MOVE_TURN) DK(rows)(P, f, 1, MOVE_TURN, cs, sn, out, nw);
        else if (move == MOVE_SLIDE) DK(rows)(P, f, 1, MOVE_SLIDE, cs, sn, out, nw);
        else DK(rows)(P, f, 1, MOVE_NONE, cs, sn, out, nw);
    } else {
        if (move == MOVE_TURN) DK(rows)(P, f, 0, MOVE_TURN, cs, sn, out, nw);
        else if (move == MOVE_SLIDE) DK(rows)(P, f, 0, MOVE_SLIDE, cs, sn, out, nw);
        else DK(rows)(P, f, 0, MOVE_NONE, cs, sn, out, nw);
    }
}

/* Jacobian column (3.30) of the joint whose motion axis is axis `ax` of frame A (its column ax, 2 = z, and
 * origin, 12 x W lanes) for the end frame E: m [z x (p_e - p); z] (turn) or m [z; 0] (slide), into rows
 * col + r step, r = 0 .. 5; the first joint to reach a column writes it (no clearing per block), the others
 * (mimic joints) add. turn, first and ax are constants where this is inlined (R and P: ax = 2). */
static inline __attribute__((always_inline)) void DK(column)(const real *restrict A, const real *restrict E,
                                                             const real m, const int turn, const int first,
                                                             const int ax, real *restrict col,
                                                             const size_t step, const int nw) {
    const real *restrict z0 = A + ax * W, *restrict z1 = A + (4 + ax) * W, *restrict z2 = A + (8 + ax) * W;
    const real *restrict p0 = A + 3 * W, *restrict p1 = A + 7 * W, *restrict p2 = A + 11 * W;
    const real *restrict e0 = E + 3 * W, *restrict e1 = E + 7 * W, *restrict e2 = E + 11 * W;
    real *restrict c0 = col, *restrict c1 = c0 + step, *restrict c2 = c1 + step, *restrict c3 = c2 + step;
    real *restrict c4 = c3 + step, *restrict c5 = c4 + step;
#pragma omp simd
    for (int l = 0; l < nw; l++) {
        real v0, v1, v2, v3, v4, v5;
        if (turn) {
            const real d0 = e0[l] - p0[l], d1 = e1[l] - p1[l], d2 = e2[l] - p2[l];
            v0 = m * (z1[l] * d2 - z2[l] * d1);
            v1 = m * (z2[l] * d0 - z0[l] * d2);
            v2 = m * (z0[l] * d1 - z1[l] * d0);
            v3 = m * z0[l];
            v4 = m * z1[l];
            v5 = m * z2[l];
        } else {
            v0 = m * z0[l];
            v1 = m * z1[l];
            v2 = m * z2[l];
            v3 = v4 = v5 = 0;
        }
        if (first) {
            c0[l] = v0; c1[l] = v1; c2[l] = v2; c3[l] = v3; c4[l] = v4; c5[l] = v5;
        } else {
            c0[l] += v0; c1[l] += v1; c2[l] += v2; c3[l] += v3; c4[l] += v4; c5[l] += v5;
        }
    }
}

/* F (12 x W lanes) . Rot(Q) in place, Q the quaternion (w, x, y, z) in rows Q, Q + W, .. (W lanes each),
 * normalised first (one of norm <= small is the identity, as diffkin._numerics.stable_normalize; scaled by
 * its largest |entry| before the squares, so entries of 1e160 (1e30 in float32) do not overflow): the S
 * motion. Column c of the result is sum_k F[:, k] R[k][c], R of (2.33); p is unchanged. */
static void DK(quaternion_turn)(const real *restrict Q, real *restrict F, const real small, const int nw) {
    real R[9][W];
#pragma omp simd
    for (int l = 0; l < nw; l++) {
        const real w0 = Q[l], x0 = Q[W + l], y0 = Q[2 * W + l], z0 = Q[3 * W + l];
        const real aw = w0 < 0 ? -w0 : w0, ax = x0 < 0 ? -x0 : x0, ay = y0 < 0 ? -y0 : y0, az = z0 < 0 ? -z0 : z0;
        const real m1 = aw > ax ? aw : ax, m2 = ay > az ? ay : az, mx = m1 > m2 ? m1 : m2;
        const real back = mx > small ? mx : 1, sc = 1 / back; /* below small: unscaled (no overflow of 1/mx) */
        const real ws = w0 * sc, xs = x0 * sc, ys = y0 * sc, zs = z0 * sc;
        const real ns = (real)sqrt((double)(ws * ws + xs * xs + ys * ys + zs * zs));
        const int tiny = !(back * ns > small);
        const real inv = tiny ? 1 : 1 / ns;
        const real e = tiny ? 1 : ws * inv, x = tiny ? 0 : xs * inv, y = tiny ? 0 : ys * inv;
        const real z = tiny ? 0 : zs * inv;
        R[0][l] = 2 * (e * e + x * x) - 1; R[1][l] = 2 * (x * y - e * z); R[2][l] = 2 * (x * z + e * y);
        R[3][l] = 2 * (x * y + e * z); R[4][l] = 2 * (e * e + y * y) - 1; R[5][l] = 2 * (y * z - e * x);
        R[6][l] = 2 * (x * z - e * y); R[7][l] = 2 * (y * z + e * x); R[8][l] = 2 * (e * e + z * z) - 1;
    }
    for (int r = 0; r < 3; r++) {
        real *restrict X = F + 4 * r * W, *restrict Y = X + W, *restrict Z = Y + W;
#pragma omp simd
        for (int l = 0; l < nw; l++) {
            const real x = X[l], y = Y[l], z = Z[l];
            X[l] = x * R[0][l] + y * R[3][l] + z * R[6][l];
            Y[l] = x * R[1][l] + y * R[4][l] + z * R[7][l];
            Z[l] = x * R[2][l] + y * R[5][l] + z * R[8][l];
        }
    }
}

/* out = P . Pre . Rot(Q): the frame of an S motion (not inlined: the R/P loop of DK(block) stays as it was). */
static __attribute__((noinline)) void DK(ball_frame)(const real *P, const DK(Fix) *pre, const real *Q, real *out,
                                                     const int nw) {
    DK(apply)(P, pre, MOVE_NONE, NULL, NULL, out, nw);
    DK(quaternion_turn)(Q, out, DK_QSMALL, nw);
}

/* The end frames (sc->ends, K x 12 x W) and, if jac, their Jacobians (sc->Jb, K x 6nv x W) of the
 * configurations in sc->qlanes (n x W). The motion axis of joint j (its z and origin, before Post; the x, y,
 * z axes of an S frame) is read from F_j, or from A_j where the joint has a Post. */
static inline __attribute__((always_inline)) void DK(block_lanes)(const Shape *s, const DK(Params) *pp,
                                                                  DK(Scratch) *sc, int jac, const int nw,
                                                                  const int ends) {
    const int J = s->J, K = s->K, nv = s->nv;
    real *F = sc->F;
    for (int j = 0; j < J; j++) {
        const real *P = s->parent[j] < 0 ? sc->basef : F + (size_t)s->parent[j] * 12 * W;
        const real m = pp->mult[j], b = pp->qoff[j];
        const real *qj = sc->qlanes + (size_t)s->qidx[j] * W;
        const int mo = s->motion[j], rev = mo == DK_MOTION_R; /* the one dispatch on a frame's motion */
        real ang[W], sn[W], cs[W];
        for (int l = 0; l < nw; l++) ang[l] = qj[l] * m + b;
        if (rev) DK_SINCOS(ang, sn, cs, nw);
        real *Fj = F + (size_t)j * 12 * W, *out = s->has_post[j] ? sc->A + (size_t)j * 12 * W : Fj;
        if (mo == DK_MOTION_S) DK(ball_frame)(P, pp->fix + j, qj, out, nw);
        else DK(apply)(P, pp->fix + j, rev ? MOVE_TURN : MOVE_SLIDE, rev ? cs : ang, sn, out, nw);
        if (s->has_post[j]) DK(apply)(out, pp->fix + J + j, MOVE_NONE, NULL, NULL, Fj, nw);
    }
    for (int k = 0; k < K && (ends || jac); k++) { /* without ends: the joint frames F only (the planner's) */
        const int e = s->end_joint[k];
        const real *P = e < 0 ? sc->basef : F + (size_t)e * 12 * W;
        real *E = sc->ends + (size_t)k * 12 * W;
        if (s->has_end[k]) DK(apply)(P, pp->fix + 2 * J + k, MOVE_NONE, NULL, NULL, E, nw);
        else memcpy(E, P, sizeof(real) * 12 * W);
        if (!jac) continue;
        real *Jb = sc->Jb + (size_t)k * 6 * nv * W;
        for (int j = 0; j < J; j++) {
            if (!s->anc[k * J + j]) continue;
            const real *Aj = (s->has_post[j] ? sc->A : F) + (size_t)j * 12 * W;
            real *col = Jb + (size_t)s->vidx[j] * W;
            const real m = pp->mult[j];
            const int first = pp->first[k * J + j], mo = s->motion[j];
            if (mo == DK_MOTION_S) { /* three turns about the rotated frame's axes, never coupled */
                for (int ax = 0; ax < 3; ax++) DK(column)(Aj, E, 1, 1, 1, ax, col + (size_t)ax * W, (size_t)nv * W, nw);
            } else if (mo == DK_MOTION_R) {
                if (first) DK(column)(Aj, E, m, 1, 1, 2, col, (size_t)nv * W, nw);
                else DK(column)(Aj, E, m, 1, 0, 2, col, (size_t)nv * W, nw);
            } else {
                if (first) DK(column)(Aj, E, m, 0, 1, 2, col, (size_t)nv * W, nw);
                else DK(column)(Aj, E, m, 0, 0, 2, col, (size_t)nv * W, nw);
            }
        }
    }
}

/* DK(block_lanes) of all W lanes, and of the first WN (one or two vector registers: the IK solve's single
 * target runs on lane 0; the other lanes' outputs are then not meaningful). */
static void DK(block)(const Shape *s, const DK(Params) *pp, DK(Scratch) *sc, int jac) {
    DK(block_lanes)(s, pp, sc, jac, W, 1);
}

static void DK(block_narrow)(const Shape *s, const DK(Params) *pp, DK(Scratch) *sc, int jac) {
    DK(block_lanes)(s, pp, sc, jac, WN, 1);
}

/* DK(block) and DK(block_narrow) without the end frames: the joint frames in sc->F only (the planner, whose
 * ends are joint frames without an offset, reads them there: no copy of 12 W reals an end) */
static void DK(block_frames)(const Shape *s, const DK(Params) *pp, DK(Scratch) *sc) {
    DK(block_lanes)(s, pp, sc, 0, W, 0);
}

static void DK(block_frames_narrow)(const Shape *s, const DK(Params) *pp, DK(Scratch) *sc) {
    DK(block_lanes)(s, pp, sc, 0, WN, 0);
}

/* Row l < nl of out (rows stride apart) gets lane l of the rows x W lanes of src: the transpose into the
 * caller's batch-first layout. */
static void DK(store_lanes)(const real *restrict src, int rows, int nl, real *restrict out, int64_t stride) {
    int r0 = 0;
#if defined(__AVX2__)
    if (nl == W) /* full blocks: DK_TILE x DK_TILE register tiles, the rows left over one by one */
        for (; r0 + DK_TILE <= rows; r0 += DK_TILE)
            for (int l = 0; l < W; l += DK_TILE) DK_TRANSPOSE(src + r0 * W + l, W, out + l * stride + r0, stride);
#endif
    src += r0 * W;
    out += r0;
    rows -= r0;
    for (int l = 0; l < nl; l++) {
        const real *restrict in = src + l;
        real *restrict o = out + l * stride;
        for (int r = 0; r < rows; r++) o[r] = in[r * W];
    }
}

/* The nl <= WN configurations q[0 .. nl - 1] into lanes 0 .. WN - 1 of sc->qlanes, the lanes from nl on repeating
 * lane nl - 1, for DK(block_narrow) and DK(block_frames_narrow), which read those lanes only (not checked for
 * NaN: the planner's own samples, between finite ends). */
static void DK(load_q_narrow)(const Shape *s, DK(Scratch) *sc, const real *q, int nl) {
    const int n = s->n;
    real *restrict ql = sc->qlanes;
    for (int l = 0; l < WN; l++) {
        const real *restrict qr = q + (l < nl ? l : nl - 1) * n;
        for (int i = 0; i < n; i++) ql[i * W + l] = qr[i];
    }
}

/* Load lanes b0 .. b0 + nl - 1 of q (B, n) into sc->qlanes (the tail repeats the last row); returns the
 * number of non-finite entries. */
static int64_t DK(load_q)(const Shape *s, DK(Scratch) *sc, const real *q, int64_t b0, int nl) {
    const int n = s->n;
    real *restrict ql = sc->qlanes;
    if (nl == W) { /* a full block: constant trip counts, vector stores and a vector count */
        real flags[W] = {0};
        for (int i = 0; i < n; i++) {
            real *restrict qi = ql + i * W;
            for (int l = 0; l < W; l++) qi[l] = q[(b0 + l) * n + i];
#pragma omp simd
            for (int l = 0; l < W; l++) flags[l] += fabs(qi[l]) <= DK_MAX ? 0 : 1; /* NaN or inf */
        }
        int64_t bad = 0;
        for (int l = 0; l < W; l++) bad += (int64_t)flags[l];
        return bad;
    }
    int64_t bad = 0;
    for (int l = 0; l < W; l++) { /* the tail repeats the last row */
        const real *restrict qr = q + (b0 + (l < nl ? l : nl - 1)) * n;
        for (int i = 0; i < n; i++) {
            ql[i * W + l] = qr[i];
            bad += l < nl && !isfinite(qr[i]);
        }
    }
    return bad;
}

/* Block blk of dk_fk: its configurations of q (B, n) into T and Jac (NULL: no Jacobian); returns the number
 * of non-finite entries of q it read. */
/* The first nl lanes of the block just evaluated (DK(block)) into T (nl, K, 4, 4) and, when Jac is not NULL,
 * Jac (nl, K, 6, nv), batch first. */
static void DK(fk_store)(const Shape *s, const DK(Scratch) *sc, int nl, real *T, real *Jac) {
    const int K = s->K, nv = s->nv;
    for (int k = 0; k < K; k++) {
        const real *E = sc->ends + (size_t)k * 12 * W;
        DK(store_lanes)(E, 12, nl, T + k * 16, (int64_t)K * 16);
        for (int l = 0; l < nl; l++) {
            real *To = T + ((int64_t)l * K + k) * 16;
            To[12] = 0; To[13] = 0; To[14] = 0; To[15] = 1;
        }
        if (Jac)
            DK(store_lanes)(sc->Jb + (size_t)k * 6 * nv * W, 6 * nv, nl, Jac + (int64_t)k * 6 * nv,
                            (int64_t)K * 6 * nv);
    }
}

static int64_t DK(fk_block)(const Shape *s, const DK(Params) *pp, DK(Scratch) *sc, const real *q, real *T,
                            real *Jac, int64_t B, int64_t blk) {
    const int K = s->K, nv = s->nv;
    const int64_t b0 = blk * W;
    const int nl = (int)(B - b0 < W ? B - b0 : W);
    const int64_t bad = DK(load_q)(s, sc, q, b0, nl);
    DK(block)(s, pp, sc, Jac != NULL);
    DK(fk_store)(s, sc, nl, T + b0 * K * 16, Jac ? Jac + b0 * K * 6 * (int64_t)nv : NULL);
    return bad;
}

/* T (B, K, 4, 4) and, when Jac is not NULL, J (B, K, 6, n) of q (B, n); returns the number of non-finite
 * entries of q (their outputs are not meaningful), or -1 when memory ran out. */
/* The threads' work spaces: nthreads blocks of at least per reals, each starting on its own 4 KiB page
 * (*stride: the reals from one to the next). Adjacent unaligned blocks shared cache lines, and two threads
 * writing their scratch then ran at 1.2x one thread instead of 1.5x (FK at batch 100 000). NULL when
 * memory ran out; free() releases it. */
static real *DK(team_alloc)(size_t per, int nthreads, size_t *stride) {
    const size_t page = 4096 / sizeof(real);
    *stride = (per + page - 1) / page * page;
    return (real *)aligned_alloc(4096, sizeof(real) * *stride * (size_t)(nthreads > 0 ? nthreads : 1));
}

static int64_t DK(dk_fk)(const dk_args *a) {
    Shape s;
    read_shape(a, &s);
    DK(Params) pp;
    if (DK(read_params)(a, &s, &pp)) return -1;
    const real *q = (const real *)a->q;
    real *T = (real *)a->T, *Jac = (real *)a->jac;
    const int64_t B = a->batch;
    int nthreads = (int)a->nthreads;
    const int64_t nblocks = (B + W - 1) / W;
    int64_t bad = 0;
    if (nthreads < 1 || B <= SERIAL_MAX) nthreads = 1;
    size_t per;
    real *all = DK(team_alloc)(DK(scratch_size)(&s) / sizeof(real), nthreads, &per); /* before the team */
    if (!all) { free(pp.fix); return -1; }
    if (nthreads == 1) { /* no team: starting one costs as much as a small batch */
        DK(Scratch) sc;
        DK(scratch_init)(&s, &pp, all, &sc);
        for (int64_t blk = 0; blk < nblocks; blk++) bad += DK(fk_block)(&s, &pp, &sc, q, T, Jac, B, blk);
    } else {
#pragma omp parallel num_threads(nthreads) reduction(+ : bad)
        {
            DK(Scratch) sc;
            DK(scratch_init)(&s, &pp, all + per * (size_t)thread_id(), &sc);
#pragma omp for schedule(dynamic, 8)
            for (int64_t blk = 0; blk < nblocks; blk++) bad += DK(fk_block)(&s, &pp, &sc, q, T, Jac, B, blk);
        }
    }
    free(all);
    free(pp.fix);
    return bad;
}

/* dk_fk_one's work space in a dk_watch: the plans, then (aligned) one thread's scratch. */
static size_t DK(work_split)(const Shape *s) {
    return (DK(params_bytes)(s) + 63) / 64 * 64;
}

static int64_t DK(dk_fk_work_bytes)(const dk_args *a) {
    Shape s;
    read_shape(a, &s);
    return (int64_t)(DK(work_split)(&s) + DK(scratch_size)(&s));
}

/* dk_fk of a (one thread) in w's work space: planned and zeroed by the first call, reused as they are by
 * the next (every block overwrites what it reads; Jacobian columns no joint reaches stay 0). */
static int64_t DK(dk_fk_work)(const dk_args *a, dk_watch *w) {
    Shape s;
    read_shape(a, &s);
    DK(Params) pp;
    DK(Scratch) sc;
    real *buf = (real *)((char *)w->work + DK(work_split)(&s));
    DK(bind_params)(a, &s, &pp, w->work);
    if (w->ready) {
        DK(scratch_bind)(&s, buf, &sc);
    } else {
        DK(plan_params)(a, &s, &pp);
        DK(scratch_init)(&s, &pp, buf, &sc);
        w->ready = 1;
    }
    int64_t bad = 0;
    for (int64_t blk = 0; blk < (a->batch + W - 1) / W; blk++)
        bad += DK(fk_block)(&s, &pp, &sc, (const real *)a->q, (real *)a->T, (real *)a->jac, a->batch, blk);
    return bad;
}

/* The rotation-vector error theta r (kernels/pose_error.py's "rotvec") of lane l of the end frame E (12 x W
 * lanes) against the target's rotation columns cols[a][c * stride] into eo[3]; returns theta:
 * v = (x_e x x_d + y_e x y_d + z_e x z_d) / 2, cos theta = (x_e.x_d + y_e.y_d + z_e.z_d - 1) / 2. */
static real DK(rotvec)(const real *E, int l, const real *const cols[3], int64_t stride, real *eo) {
    real v[3] = {0, 0, 0}, tr = 0;
    for (int a = 0; a < 3; a++) {
        real de[3], ee[3];
        for (int c = 0; c < 3; c++) {
            de[c] = cols[a][c * stride];
            ee[c] = E[(4 * c + a) * W + l];
        }
        v[0] += ee[1] * de[2] - ee[2] * de[1];
        v[1] += ee[2] * de[0] - ee[0] * de[2];
        v[2] += ee[0] * de[1] - ee[1] * de[0];
        tr += ee[0] * de[0] + ee[1] * de[1] + ee[2] * de[2];
    }
    for (int c = 0; c < 3; c++) v[c] *= (real)0.5;
    const real vv = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
    const real sth = (real)sqrt((double)(vv > DK_TINY ? vv : DK_TINY));
    const real th = (real)atan2((double)sth, (double)((real)0.5 * (tr - 1)));
    for (int c = 0; c < 3; c++) eo[c] = v[c] * (th / sth);
    return th;
}

/* minimum and maximum that propagate NaN as torch.minimum / torch.maximum / amin / clamp do (the C twins of
 * torch code that must give the same floats: _native_clip.c, _native_topp.c) */
static inline real DK(nan_min)(real a, real b) { return (a < b || a != a) ? a : b; }
static inline real DK(nan_max)(real a, real b) { return (a > b || a != a) ? a : b; }

#include "_native_solve.c"
#include "_native_collide.c"
#include "_native_plan.c"
#include "_native_velocity.c"
#include "_native_banded.c"
#include "_native_clip.c"
/* the C twins of torch code that must give the same floats (each operation a statement of its own, never
   contracted into a fused multiply-add): compiled with contraction off */
#if defined(__clang__)
#pragma clang fp contract(off)
#elif defined(__GNUC__)
#pragma GCC push_options
#pragma GCC optimize("fp-contract=off")
#endif
#include "_native_topp.c"
#include "_native_spline.c" /* after _native_topp.c: its searches */
#if defined(__clang__)
#pragma clang fp contract(on)
#elif defined(__GNUC__)
#pragma GCC pop_options
#endif

#undef real
#endif
