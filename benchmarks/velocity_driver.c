/* Times the C velocity step (dk_velocity_step of the fused library) in a teleoperation loop outside Python,
 * for benchmarks/teleop_profile.py: the step's own cost without the ctypes call around it (and loop_fk
 * below: the batch-1 FK + Jacobian the step starts with).
 *
 *     loop(step, fixed, q0, q1, targets, q_ref, v, dt, reps, times)
 *
 * step: the library's dk_velocity_step; fixed: its first argument (dk_args, dk_vel, dk_watch addresses);
 * q0, q1: two (nq) buffers the loop alternates (q and q_next); targets: reps x (16 F) reals; q_ref (nq) or
 * NULL; v (nv) out; times: reps seconds out. Returns the OR of the statuses. */
#include <stdint.h>
#include <string.h>
#include <time.h>

typedef int64_t (*step_t)(const void *, const void *);

static double now(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

int64_t loop(void *step, const void *fixed, double *q0, double *q1, const double *targets, int64_t target_reals,
             const double *q_ref, double *v, double dt, int64_t reps, double *times) {
    step_t f = (step_t)step;
    int64_t status = 0;
    for (int64_t r = 0; r < reps; r++) {
        double *q = (r & 1) ? q1 : q0, *qn = (r & 1) ? q0 : q1;
        unsigned char call[6 * 8];
        const uint64_t p[5] = {(uint64_t)(uintptr_t)q, (uint64_t)(uintptr_t)(targets + r * target_reals),
                               (uint64_t)(uintptr_t)q_ref, (uint64_t)(uintptr_t)v, (uint64_t)(uintptr_t)qn};
        memcpy(call, p, sizeof p);
        memcpy(call + sizeof p, &dt, sizeof dt);
        const double t0 = now();
        status |= f(fixed, call);
        times[r] = now() - t0;
    }
    return status;
}

/* The batch-1 FK + Jacobian alone: fk is the library's dk_fk_one(dk_args, dk_watch, q, T, J). */
int64_t loop_fk(void *fk, const void *base, void *watch, const double *q, double *T, double *J, int64_t reps,
                double *times) {
    int64_t (*f)(const void *, void *, const void *, void *, void *) =
        (int64_t (*)(const void *, void *, const void *, void *, void *))fk;
    int64_t status = 0;
    for (int64_t r = 0; r < reps; r++) {
        const double t0 = now();
        status |= f(base, watch, q, T, J);
        times[r] = now() - t0;
    }
    return status;
}
