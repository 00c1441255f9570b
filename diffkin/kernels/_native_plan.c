/* RRT-Connect per planning problem in C (included by _native.c once per real type, after
 * _native_collide.c): the search stage of diffkin.motion.plan (diffkin/motion/_native_search.py) for
 * problems spread over OpenMP threads, one problem per thread at a time.
 *
 * Per problem (VAMP's RRT-Connect), timed by a monotonic clock read in its thread (nanoseconds: as VAMP's
 * planners time themselves): with `ends`, its start and goal decided at the resolution ladder first
 * (DK(plan_ends)); the straight edge start -> goal; then of the trees rooted at the start and the goal the
 * one with fewer nodes (the start's on a tie: balanced trees, stricter than VAMP's balance, which takes turns
 * unless one tree has twice the other's nodes; the tree whose root sits in a pocket gets the iterations until
 * it has grown as large as the other, where taking turns let the free tree grow large, and its nearest-node
 * scans slow, on the hard problems) extends its node nearest to a uniform sample of the box [lo, hi] (the
 * other tree's root with probability goal_bias) by at most `step` (in the bound's metric sum_j R_j |dq_j|:
 * metres of geom travel) when that whole edge is clear, and then the other tree CONNECTs (RRT-Connect's):
 * from its node nearest the new one it steps towards it in ceil(L / step) equal steps (L the distance in the
 * same metric), keeping each clear step as a node, until a step collides or the last one reaches the new
 * node and joins the trees (DK(plan_connect)). Every edge, EXTEND's and each step's, is taken whole or not
 * at all: most edges are rejected, and a rejected edge is usually caught by its first, coarse samples, where
 * keeping an edge's clear prefix meant deciding every sample in order up to the collision (docs/motion.md:
 * about 40 % fewer decisions, as many problems solved). VAMP's CONNECT steps alike, from the new node towards
 * the other tree's nearest; CONNECT by one whole straight edge, as here before, took 7 % more search time at
 * the median problem (the first 8 MotionBenchMaker problems of each family, seeds 0-2), stepping from the new
 * node 3 % more.
 * With `restart` > 0, every `restart` iterations without a join both trees are dropped and grown anew from
 * the roots (the random stream continuing); motion.plan passes 0 (never): restarts did not help on the
 * MotionBenchMaker problems.
 * Then random shortcuts (shortcut_tries straight edges between waypoints i < j - 1, each clear one taken).
 * Nearest: a linear scan in the weighted L1 metric of the bound (diffkin.motion._search's), vectorised over the
 * nodes (DK(plan_nearest)).
 *
 * Edges: the subdivision of diffkin.motion._edges with the problem's resolution eta_b: a straight edge
 * Delta q in ceil(sum_j R_j |Delta q_j| / (2 eta_b)) equal steps (R_j: joint_reach, passed in), every sample
 * decided by DK(collide_block) of _native_collide.c with slack eta_b (samples clear of margin + eta_b prove
 * the continuous edge clear of margin: between samples every distance is at most eta_b smaller). Samples
 * are placed by the FK block of _native.c (the chain's every
 * joint frame as an end link) and the placement columns h_c of RobotCollision._columns (each capsule end a
 * fixed point of one frame). A full edge is decided coarse, then in order (its far end first, then the
 * midpoints of ever finer halvings down to about 4 samples, then the rest along the edge: EdgeOrder), a
 * prefix in order; both in blocks of 4 growing to COLLIDE_BLOCK samples, an edge leaving at its first
 * colliding block. The search's and the shortcuts' edges are taken whole or not at all, so their blocks are
 * decided by DK(collide_any): a block stops at the first collision found in any of its samples (the same
 * verdicts as deciding every sample, the same paths; 25-30 % less time than deciding each block up to its
 * first colliding sample); such an edge of 6 sub-steps or more is decided by covers, runs of three samples
 * whose middle, clear of margin + 3 eta, proves the run (DK(plan_edge_cover)). An edge's end already known
 * clear (a tree's node, a waypoint, the goal) is not decided again. A prefix (dk_plan_edges with prefix)
 * reads a block up to its first colliding sample (DK(collide_first)): the samples past the first collision
 * found so far drop out of the later tests.
 *
 * Randomness: each problem's stream is splitmix64 seeded by the caller's seed mixed with a hash of the
 * problem's start and goal bytes, so a problem planned alone takes the same path as in any batch, on any
 * number of threads.
 *
 * Besides the search: dk_plan_decide (configurations), dk_plan_edges (straight edges, the samples of
 * diffkin.motion._edges.EdgeChecker.edges) and dk_plan_points (the shortcuts between points of
 * diffkin.motion._search.shortcut_points, its rounds per path in C).
 */
#ifndef DK_PLAN_TYPES
#define DK_PLAN_TYPES
#define DK_PLAN_PASS 1
#define DK_PLAN_VERSION 6 /* bump with every change of DK_PLAN_FIELDS (and _native_search.py's VERSION) */
#define DK_PLAN_FOUND 1
#define DK_PLAN_NOT_FOUND 0
#define DK_PLAN_TOO_LONG 2
#define DK_PLAN_NO_MEMORY (-1)
#define DK_PLAN_START_BAD 3 /* with ends: the start clears no rung of the ladder (the goal does) */
#define DK_PLAN_GOAL_BAD 4  /* with ends: the goal clears none (the start does) */
#define DK_PLAN_ENDS_BAD 5  /* with ends: neither clears one */

#define DK_PLAN_FIELDS(X) \
    X(int64_t, version, "DK_PLAN_VERSION") \
    X(int64_t, size, "sizeof(dk_plan)") \
    X(int64_t, nthreads, "threads over the problems (at least 1)") \
    X(const dk_args *, chain, "the chain's FK, every joint frame an end link (dk_args of the real type)") \
    X(const dk_collide *, collide, "the decisions' constants (pairs, radii, world rows, skips, margin); " \
                                   "its A, B, N, ok, wid, slack are not read") \
    X(int64_t, C, "placed points: the G capsule starts then the G ends") \
    X(const int64_t *, col_frame, "[C] frame of each point: 0 the base, k >= 1 the chain's end k - 1") \
    X(const void *, col_h, "[4C] reals: each point in its frame, homogeneous") \
    X(const void *, base, "[12] reals: the base frame, 3x4 row-major") \
    X(int64_t, B, "problems") \
    X(const void *, q_start, "[B n] reals; without ends each clear of margin + eta (the caller's checks; " \
                             "not decided)") \
    X(const void *, q_goal, "[B n] reals; without ends each clear of margin + eta (the caller's checks; " \
                            "decided once more)") \
    X(const int64_t *, world, "[B] the world row of each problem, or NULL: row 0") \
    X(void *, eta, "[B] reals: each problem's resolution [m] (with ends: out)") \
    X(const void *, lo, "[n] reals: the sampling box") \
    X(const void *, hi, "[n] reals") \
    X(const void *, reach, "[n] reals: R_j of joint_reach") \
    X(double, step, "RRT range in the bound's metric [m]") \
    X(double, goal_bias, "probability of sampling the other tree's root") \
    X(int64_t, max_iterations, "RRT-Connect iterations per problem") \
    X(int64_t, restart, "iterations after which both trees are dropped and grown anew (0: never)") \
    X(int64_t, shortcut_tries, "random shortcut attempts per path") \
    X(int64_t, seed, "mixed with each problem's hash") \
    X(int64_t, capacity, "L: waypoints a returned path may have") \
    X(void *, path, "[B L n] reals out: waypoints (the rest of a row: the goal)") \
    X(int64_t *, n_way, "[B] out: waypoints") \
    X(int64_t *, status, "[B] out: DK_PLAN_FOUND, _NOT_FOUND, _TOO_LONG, _NO_MEMORY, _START_BAD, _GOAL_BAD, " \
                          "_ENDS_BAD") \
    X(int64_t *, iterations, "[B] out: RRT-Connect iterations run") \
    X(int64_t *, checked, "[B] out: configurations decided") \
    X(int64_t *, nodes, "[B] out: the two trees' nodes at the end, or NULL") \
    X(int64_t, N, "dk_plan_decide: configurations") \
    X(const void *, q, "dk_plan_decide: [N n] reals") \
    X(const int64_t *, wid, "dk_plan_decide: [N] the world row of each, or NULL: row 0") \
    X(double, slack, "dk_plan_decide: clear means every distance - margin >= slack") \
    X(uint8_t *, ok, "dk_plan_decide: [N] out") \
    X(const void *, qb, "dk_plan_edges: [N n] reals, the edges' far ends (q: their starts)") \
    X(const int64_t *, steps, "dk_plan_edges: [N] each edge's sub-steps (at least 1)") \
    X(const void *, slacks, "dk_plan_edges: [N] reals, each edge's slack (its problem's resolution)") \
    X(int64_t, prefix, "dk_plan_edges: 1: samples in order along each edge, 0: coarse, then in order") \
    X(int64_t *, first_bad, "dk_plan_edges: [N] out: a colliding sample (with prefix the first; steps + 1: none)") \
    X(const int64_t *, keys, "dk_plan_points: [B] each path's random-stream key (_search.row_keys)") \
    X(int64_t, rounds, "dk_plan_points: rounds of shortcuts between points") \
    X(int64_t, tries, "dk_plan_points: shortcuts tried per path and round") \
    X(int64_t, stop_after, "dk_plan_points: a path stops after this many rounds in a row without one") \
    X(int64_t, ends, "dk_plan_search: 0: eta given; k >= 1: each problem's start and goal decided at " \
                     "resolution / 2^i, i < k, eta[b] set to the finest rung either needed (DK(plan_ends))") \
    X(double, resolution, "dk_plan_search with ends: the ladder's top rung [m]") \
    X(int64_t *, nanoseconds, "dk_plan_search: [B] out: each problem's wall time, a monotonic clock read in " \
                              "its thread, or NULL") \
    X(int64_t, no_hints, "1: no collisions remembered between blocks (DK(plan_decide)'s hints: they change " \
                         "no verdict, only how soon a colliding block is found)") \
    X(int64_t *, hinted, "dk_plan_search: [B] out: blocks found colliding by a remembered collision alone " \
                         "(the search's and its shortcuts'), or NULL")

#define DK_PDECLARE(type, name, what) type name;
typedef struct dk_plan { DK_PLAN_FIELDS(DK_PDECLARE) } dk_plan;
#undef DK_PDECLARE
DK_LAYOUT(plan, dk_plan, DK_PLAN_FIELDS, DK_PLAN_VERSION) /* dk_layout_plan, dk_names_plan (_native.c) */

/* The order in which an edge's samples i (of its ns sub-steps) are decided, from sample `from` (0: the edge's
 * start included, 1: known clear) to ns (with `last`; without, ns is known clear and skipped): with prefix in
 * order along the edge; else coarse, then in order: `from` (when 0), ns (with `last`), the odd multiples of
 * ever smaller powers of two down to the stride that leaves about EDGE_COARSE of them (a colliding edge is
 * usually caught among these), then the other samples in order along the edge (consecutive samples lie close
 * together, so a block's bounding boxes stay tight and its culling works; all the way coarse to fine the late
 * blocks spanned the whole edge: 10-25 % more time on the first 20 MotionBenchMaker problems of each family).
 * Edges of fewer than 2 EDGE_COARSE samples go coarse to fine all the way. EDGE_COARSE was 16, coarse to fine
 * below 256 samples, which left every search edge (about 34 cover runs at step 1.0) coarse to fine all the
 * way: 4 (and the ends) took 6 % less search time on the first 5 MotionBenchMaker problems of each family for
 * the same paths (1.4 % more decisions); 2 did no better. */
typedef struct {
    int64_t ns, top, level, next, seq, stride;
    int stage, prefix, last;
} EdgeOrder;
#define EDGE_COARSE 4 /* samples of an edge's coarse pass besides its ends, about (EdgeOrder) */

static void edge_order_init(EdgeOrder *o, int64_t ns, int prefix, int from, int last) {
    o->ns = ns, o->prefix = prefix, o->last = last, o->seq = from, o->stage = from, o->next = 0;
    o->top = 1;
    while (o->top * 2 <= ns) o->top *= 2;
    o->level = o->top;
    o->stride = o->top >= 2 * EDGE_COARSE ? o->top / EDGE_COARSE : 1;
}

/* The next samples, at most size of them, into idx; returns how many (0: the edge is done). */
static int edge_order_fill(EdgeOrder *o, int64_t *idx, int size) {
    int m = 0;
    while (m < size) {
        int64_t i;
        if (o->prefix) {
            if (o->seq > o->ns - !o->last) break;
            i = o->seq++;
        } else if (o->stage < 2) {
            i = o->stage++ ? o->ns : 0;
            if (i == o->ns && !o->last) continue;
        } else if (o->level >= o->stride) {
            if (o->next == 0) o->next = o->level;
            i = o->next;
            o->next += o->level == o->top ? o->level : 2 * o->level;
            if (o->next > o->ns) { o->level >>= 1; o->next = o->level; }
            if (o->level < o->stride) o->seq = o->stride > 1 ? 1 : o->ns; /* stride 1: every sample taken */
            if (i == o->ns) continue;
        } else {
            if (o->seq >= o->ns) break;
            i = o->seq++;
            if (i % o->stride == 0) continue;
        }
        idx[m++] = i;
    }
    return m;
}

/* The threads of a call asking for `requested` over `items` independent items: at most one per item. */
static inline int plan_threads(int64_t requested, int64_t items) {
    return (int)(requested > 1 && items > 1 ? (requested < items ? requested : items) : 1);
}

static inline uint64_t plan_finalise(uint64_t z) { /* splitmix64's finaliser (_search._mix) */
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
}

static inline uint64_t plan_mix(uint64_t *state) { /* splitmix64 */
    return plan_finalise(*state += 0x9E3779B97F4A7C15ull);
}

static inline double plan_uniform(uint64_t *state) { return (double)(plan_mix(state) >> 11) * 0x1.0p-53; }

static inline int64_t plan_clock(void) { /* ns of a monotonic clock (0 where there is none) */
#ifdef CLOCK_MONOTONIC
    struct timespec t;
    if (clock_gettime(CLOCK_MONOTONIC, &t) == 0) return (int64_t)t.tv_sec * 1000000000 + (int64_t)t.tv_nsec;
#endif
    return 0;
}

static uint64_t plan_hash(const void *a, const void *b, size_t bytes, int64_t seed) { /* FNV-1a, then mixed */
    uint64_t h = 1469598103934665603ull;
    for (size_t i = 0; i < bytes; i++) h = (h ^ ((const uint8_t *)a)[i]) * 1099511628211ull;
    for (size_t i = 0; i < bytes; i++) h = (h ^ ((const uint8_t *)b)[i]) * 1099511628211ull;
    uint64_t s = h ^ (uint64_t)seed * 0xD1B54A32D192ED03ull;
    return plan_mix(&s);
}
#else
#undef DK_PLAN_PASS
#define DK_PLAN_PASS 2
#endif

#define COVER_MIN_STEPS 6 /* shorter edges: every sample decided (DK(plan_edge_bad)) */
#define PLAN_HINTS 16 /* sphere-object collisions remembered (one: 43 % of first blocks stop at it; four: 8-10 %
                         * less time again; 16 and the cylinders' too: 5-9 % less again, 32 no more) */
typedef struct { /* one thread's work space */
    const dk_plan *p;
    Shape s;
    const DK(Params) *pp;
    DK(Scratch) sc;
    dk_collide cc;        /* the problem's decisions: A, B, N, wid, slack set here */
    CollideRuns runs;     /* cc's geoms grouped by frame, its pairs by pair of groups */
    real *qs;             /* [COLLIDE_BLOCK n] the block's configurations */
    real *P;              /* [C 3 N] the placed points, component-major, N = cc.N (DK(plan_rows)) */
    int64_t *wid;         /* [COLLIDE_BLOCK] the problem's world row */
    uint8_t ok[COLLIDE_BLOCK];
    uint8_t hi[COLLIDE_BLOCK]; /* with COLLIDE_COVER: clear of the cover's slack too (DK(plan_edge_cover)) */
    real *cols[2];        /* [n cap] the trees' nodes, joint-major (DK(plan_nearest) reads them vectorised) */
    int64_t *parent[2];   /* [cap] */
    real *path;           /* [2 cap n] */
    int64_t cap, cap_max, checked; /* the trees' node capacity now and at most (DK(plan_search_one)) */
    int64_t hinted;       /* blocks found colliding by a hint alone (dk_plan's hinted) */
    int points;           /* every capsule a sphere (ends equal): B is A, placed once */
    CollideHint hint[PLAN_HINTS]; /* the last sphere-object collisions of the narrow decisions, latest first */
    int plain_ends;        /* every end frame a joint's frame (or the base) without an offset, at most 64 of
                            * them: the FK leaves the ends uncopied (DK(block_frames)), read through endf */
    const real *endf[64];  /* with plain_ends, end frame k's rows in w->sc (12 x W): sc.F's or sc.basef's */
    real *scratch;
    real eta;
    uint64_t rng;
} DK(PlanWork);

/* Place point c of lanes b0 .. b0 + nl - 1 (w->P) from the FK block just computed in w->sc (its lanes 0 ..
 * nl - 1). */
static inline __attribute__((always_inline)) void DK(plan_place_point)(DK(PlanWork) *w, int64_t c, int b0, int nl) {
    const dk_plan *p = w->p;
    const real *h = (const real *)p->col_h, *base = (const real *)p->base;
    const int64_t f = p->col_frame[c];
    const real h0 = h[4 * c], h1 = h[4 * c + 1], h2 = h[4 * c + 2], h3 = h[4 * c + 3];
    const int64_t N = w->cc.N;
    real *dst = w->P + c * 3 * N + b0;
    if (f == 0) {
        for (int r = 0; r < 3; r++) {
            const real v = base[4 * r] * h0 + base[4 * r + 1] * h1 + base[4 * r + 2] * h2 + base[4 * r + 3] * h3;
            for (int l = 0; l < nl; l++) dst[r * N + l] = v;
        }
        return;
    }
    const real *E = w->plain_ends ? w->endf[f - 1] : w->sc.ends + (size_t)(f - 1) * 12 * W;
    /* four lanes at a time (DK(v4) of _native_collide.c; a loop of 4 lanes stays scalar), up to the next
     * multiple of 4: the FK block's W lanes and the rows of w->P (DK(plan_rows)) leave room, and the lanes
     * past nl are read by no decision */
    _Static_assert(W % 4 == 0 && COLLIDE_BLOCK % W == 0, "a block's lanes in whole vectors of 4");
    for (int r = 0; r < 3; r++) {
        const real *E0 = E + 4 * r * W, *E1 = E0 + W, *E2 = E1 + W, *E3 = E2 + W;
        real *restrict o = dst + r * N;
        for (int l = 0; l < nl; l += 4) {
            const DK(v4) x = DK(v4_load)(E0, l, W, 1) * h0 + DK(v4_load)(E1, l, W, 1) * h1 +
                             DK(v4_load)(E2, l, W, 1) * h2 + DK(v4_load)(E3, l, W, 1) * h3;
            memcpy(o + l, &x, sizeof x);
        }
    }
}

/* Forget the remembered collisions (a hint changes no verdict, only how soon a colliding block is found). */
static inline void DK(plan_forget_hints)(DK(PlanWork) *w) {
    for (int k = 0; k < PLAN_HINTS; k++) w->hint[k].w = -1;
}

/* x to the front of the hints, those before position k moved one back (k = PLAN_HINTS - 1: a new one, the
 * oldest dropped). */
static inline void DK(plan_hint_to_front)(DK(PlanWork) *w, CollideHint x, int k) {
    memmove(w->hint + 1, w->hint, sizeof(CollideHint) * (size_t)k);
    w->hint[0] = x;
}

/* Place every geom (spheres: the starts only, the ends are the same points). */
static inline __attribute__((always_inline)) void DK(plan_place)(DK(PlanWork) *w, int b0, int nl) {
    for (int64_t c = 0; c < (w->points ? w->p->C / 2 : w->p->C); c++) DK(plan_place_point)(w, c, b0, nl);
}

/* The rows of w->P for a decision of m configurations: m rounded up to a multiple of 4 lanes each (cc.N), so
 * that a block's points lie together: rows COLLIDE_BLOCK apart (2 KiB of doubles) put the 4 lanes of an
 * edge's first block, in each of a spherized Panda's 177 rows, into the same two sets of a 48 KiB 12-way L1
 * cache, where they evicted each other before the boxes', the objects' and the self pairs' tests read them
 * back (rows 64 bytes longer than that took 0.93 of the search's time, packed rows 0.98 of that again). */
static inline void DK(plan_rows)(DK(PlanWork) *w, int m) {
    w->cc.N = (m + 3) & ~3;
    w->cc.B = w->points ? w->P : w->P + w->cc.G * 3 * w->cc.N;
}

/* Decide the m configurations of w->qs into w->ok (1: clear with margin + eta); mode as DK(collide_lanes)'s:
 * with COLLIDE_FIRST ok is exact only up to its first 0, with COLLIDE_ANY only whether it has a 0; with
 * COLLIDE_COVER as COLLIDE_ANY, and where ok has no 0, w->hi says which are clear of margin + COVER_SLACK
 * eta as well. */
static void DK(plan_decide)(DK(PlanWork) *w, int m, int mode) {
    _Static_assert(COLLIDE_NARROW == WN, "the narrow decision places DK(block_narrow)'s lanes");
    if (m <= 0) return;
    DK(plan_rows)(w, m);
    const real thr_hi = (real)(w->cc.margin + COVER_SLACK * w->cc.slack);
    if ((mode == COLLIDE_ANY || mode == COLLIDE_COVER) && m <= COLLIDE_NARROW) {
        /* a block of 4 samples or fewer (an edge's first; the last of a short edge): COLLIDE_NARROW lanes,
         * whatever m (constant trip counts in every loop of the decision), the lanes from m on repeating
         * lane m - 1 (DK(load_q_narrow)) */
        DK(load_q_narrow)(&w->s, &w->sc, w->qs, m);
        if (w->plain_ends) DK(block_frames_narrow)(&w->s, w->pp, &w->sc);
        else DK(block_narrow)(&w->s, w->pp, &w->sc, 0);
        memset(w->ok, 1, COLLIDE_NARROW);
        int hit = 0; /* the last collisions' spheres and boxes first, each sphere placed alone */
        for (int k = 0; w->points && k < PLAN_HINTS && w->hint[k].w >= 0 && !hit; k++) {
            DK(plan_place_point)(w, w->hint[k].g, 0, COLLIDE_NARROW);
            hit = DK(collide_hint)(&w->cc, &w->hint[k], w->ok);
            if (hit) DK(plan_hint_to_front)(w, w->hint[k], k), w->hinted++;
        }
        if (!hit) {
            DK(plan_place)(w, 0, COLLIDE_NARROW);
            CollideHint found = {-1, -1, 0};
            if (mode == COLLIDE_COVER)
                DK(collide_cover_narrow)(&w->cc, &w->runs, w->ok, w->points ? &found : NULL, thr_hi, w->hi);
            else
                DK(collide_any_narrow)(&w->cc, &w->runs, w->ok, w->points ? &found : NULL);
            if (found.w >= 0 && !w->p->no_hints) DK(plan_hint_to_front)(w, found, PLAN_HINTS - 1);
        }
        for (int l = m; l < COLLIDE_NARROW; l++) w->ok[m - 1] &= w->ok[l]; /* a repeat colliding: lane m - 1 */
        for (int l = m; mode == COLLIDE_COVER && l < COLLIDE_NARROW; l++) w->hi[m - 1] &= w->hi[l];
        w->checked += m;
        return;
    }
    for (int b0 = 0; b0 < m; b0 += W) {
        const int nl = m - b0 < W ? m - b0 : W;
        DK(load_q)(&w->s, &w->sc, w->qs, b0, nl);
        if (w->plain_ends && nl <= WN) DK(block_frames_narrow)(&w->s, w->pp, &w->sc); /* 4 lanes or fewer */
        else if (w->plain_ends) DK(block_frames)(&w->s, w->pp, &w->sc);
        else if (nl <= WN) DK(block_narrow)(&w->s, w->pp, &w->sc, 0); /* (an edge's first block) */
        else DK(block)(&w->s, w->pp, &w->sc, 0);
        DK(plan_place)(w, b0, nl);
    }
    memset(w->ok, 1, (size_t)m);
    if (mode == COLLIDE_COVER) DK(collide_cover)(&w->cc, &w->runs, 0, m, w->ok, thr_hi, w->hi);
    else if (mode == COLLIDE_ANY) DK(collide_any)(&w->cc, &w->runs, 0, m, w->ok);
    else if (mode == COLLIDE_FIRST) DK(collide_first)(&w->cc, &w->runs, 0, m, w->ok);
    else DK(collide_block)(&w->cc, &w->runs, 0, m, w->ok);
    w->checked += m;
}

/* Sub-steps of the straight edge a -> b: ceil(sum_j R_j |b_j - a_j| / (2 eta)), at least 1 (every point
 * travels at most 2 eta a step: within eta of the nearer sample, diffkin.motion._edges). */
static int64_t DK(plan_steps)(const DK(PlanWork) *w, const real *a, const real *b) {
    const real *R = (const real *)w->p->reach;
    double L = 0;
    for (int j = 0; j < w->s.n; j++) L += (double)R[j] * fabs((double)(b[j] - a[j]));
    const double k = ceil(L / (2 * (double)w->eta));
    return k < 1 ? 1 : (int64_t)k;
}

/* The samples idx[0 .. m-1] (each in 0 .. ns) of the straight edge a -> b in ns sub-steps, sample i at
 * a + (i / ns) (b - a), decided into w->qs and w->ok (mode as DK(plan_decide)); returns the first colliding
 * one in the order given, or -1. */
static int64_t DK(plan_samples)(DK(PlanWork) *w, const real *a, const real *b, int64_t ns, const int64_t *idx,
                                int m, int mode) {
    const int n = w->s.n;
    for (int k = 0; k < m; k++) {
        const real f = (real)idx[k] / (real)ns;
        for (int j = 0; j < n; j++) w->qs[k * n + j] = a[j] + f * (b[j] - a[j]);
    }
    DK(plan_decide)(w, m, mode);
    for (int k = 0; k < m; k++)
        if (!w->ok[k]) return idx[k];
    return -1;
}

/* An edge taken whole or not at all (COLLIDE_ANY) decided by covers: its samples 0 .. end (ns, or ns - 1 where
 * b is known clear) in runs of three, 3k .. 3k + 2, each run's middle one (end where the run is cut short;
 * sample 0, where a is known clear, is proven with its run or left out) decided at margin + eta and at
 * margin + COVER_SLACK eta (COLLIDE_COVER) in the EdgeOrder of the runs (coarse, then in order). A middle
 * clear of the larger slack proves its run: its neighbours lie one sub-step away, where every distance is at
 * most 2 eta smaller (diffkin.motion._edges), so they are clear of margin + eta, as the subdivision asks;
 * the other samples of a run whose middle is clear of the smaller one only are decided as themselves
 * (COLLIDE_ANY, gathered into blocks). A colliding sample ends the edge (returned: one that collides); ns + 1
 * when every sample is proven clear. The same verdicts as deciding every sample (the same paths; a sample
 * within rounding of a threshold aside, as anywhere in the decisions), with about
 * a third of the decisions where the robot keeps 3 eta from everything (92 % of the samples of the first
 * 5 MotionBenchMaker paths of each family at eta = 5 mm). */
static int64_t DK(plan_edge_cover)(DK(PlanWork) *w, const real *a, const real *b, int64_t ns, int from,
                                   int last) {
    /* the samples from .. end to prove, in runs over 0 .. end (b itself left out where known clear) */
    const int64_t end = last ? ns : ns - 1, runs = end / 3 + 1;
    int64_t idx[COLLIDE_BLOCK], mid[COLLIDE_BLOCK], pend[3 * COLLIDE_BLOCK];
    int np = 0, size = 4;
    EdgeOrder order;
    edge_order_init(&order, runs - 1, 0, 0, 1);
    for (;;) {
        const int m = edge_order_fill(&order, idx, size);
        for (int k = 0; k < m; k++) mid[k] = 3 * idx[k] + 1 < end ? 3 * idx[k] + 1 : end;
        int64_t bad = m ? DK(plan_samples)(w, a, b, ns, mid, m, COLLIDE_COVER) : -1;
        if (bad >= 0) return bad;
        for (int k = 0; k < m; k++) { /* the runs not proven by their middle */
            if (w->hi[k]) continue;
            const int64_t r0 = 3 * idx[k], r1 = r0 + 2 < end ? r0 + 2 : end;
            for (int64_t i = r0 > from ? r0 : from; i <= r1; i++)
                if (i != mid[k]) pend[np++] = i;
        }
        while (np >= COLLIDE_BLOCK || (np > 0 && m == 0)) { /* full blocks, then the rest at the end */
            const int take = np < COLLIDE_BLOCK ? np : COLLIDE_BLOCK;
            bad = DK(plan_samples)(w, a, b, ns, pend, take, COLLIDE_ANY);
            if (bad >= 0) return bad;
            memmove(pend, pend + take, sizeof(int64_t) * (size_t)(np - take));
            np -= take;
        }
        if (m == 0) return ns + 1;
        /* middles in blocks of 4, 16, 64, 256: a block's fixed work (its boxes, the objects' tests) is most of
         * a wide block's time, and an edge whose first 4 middles are clear is usually clear (doubling from 4:
         * 5 % fewer decisions, 3-5 % more time) */
        size = size * 4 > COLLIDE_BLOCK ? COLLIDE_BLOCK : size * 4;
    }
}

/* The straight edge a -> b in ns sub-steps, its samples i = from .. ns (ns - 1 without last) at
 * a + (i / ns) (b - a) taken in the EdgeOrder (in order with prefix, else coarse, then in order) in blocks
 * of 4 growing to COLLIDE_BLOCK (a
 * rejected edge is usually caught in its first samples; 4 decided 30-50 % fewer than 16 and took 1-15 %
 * less time on the first 20 MotionBenchMaker problems of each family), the edge
 * leaving at its first colliding block, decided in `mode` (DK(collide_lanes)): returns, with
 * COLLIDE_FIRST, the first colliding sample of that block in the order taken (with prefix the first along the
 * edge), with COLLIDE_ANY a colliding sample of it (ns + 1: every sample clear). With COLLIDE_ANY and without
 * prefix, an edge of COVER_MIN_STEPS sub-steps or more is decided by covers instead (DK(plan_edge_cover): the
 * same verdicts, fewer decisions). The samples decided are counted in w->checked. */
static int64_t DK(plan_edge_bad)(DK(PlanWork) *w, const real *a, const real *b, int64_t ns, int prefix,
                                 int from, int last, int mode) {
    if (mode == COLLIDE_ANY && !prefix && ns >= COVER_MIN_STEPS) return DK(plan_edge_cover)(w, a, b, ns, from, last);
    int64_t idx[COLLIDE_BLOCK];
    EdgeOrder order;
    edge_order_init(&order, ns, prefix, from, last);
    int size = 4;
    for (;;) {
        const int m = edge_order_fill(&order, idx, size);
        if (m == 0) return ns + 1;
        const int64_t bad = DK(plan_samples)(w, a, b, ns, idx, m, mode);
        if (bad >= 0) return bad;
        size = size * 2 > COLLIDE_BLOCK ? COLLIDE_BLOCK : size * 2;
    }
}

/* Whether every sample of the straight edge a -> b in its DK(plan_steps) is clear (an edge taken whole or not
 * at all: any collision found ends it, COLLIDE_ANY), its samples from `from` (1: a is already known clear)
 * to the last one, b, with `last` (0: b is known clear: a node of a tree, a waypoint, the goal, each decided
 * with this slack before; the edge ends at b itself, so its subdivision's proof holds). */
static int DK(plan_edge_from)(DK(PlanWork) *w, const real *a, const real *b, int from, int last) {
    const int64_t ns = DK(plan_steps)(w, a, b);
    return DK(plan_edge_bad)(w, a, b, ns, 0, from, last, COLLIDE_ANY) > ns;
}

/* DK(plan_edge_from) of an edge from a known clear a. */
static int DK(plan_edge)(DK(PlanWork) *w, const real *a, const real *b, int last) {
    return DK(plan_edge_from)(w, a, b, 1, last);
}

/* The tree node nearest q in the weighted L1 metric: cols holds the tree's count nodes joint-major (cols[j cap +
 * k], node k's joint j), so each block's distances are vectorised over the nodes, summed over the joints in
 * order as a scalar loop would; the first of equal minima wins (as a scan in node order). */
#define NEAREST_BLOCK 256
static int64_t DK(plan_nearest)(const real *cols, int64_t cap, int64_t count, const real *q, const real *R, int n) {
    int64_t best = 0;
    real bd = (real)INFINITY, d[NEAREST_BLOCK];
    for (int64_t k0 = 0; k0 < count; k0 += NEAREST_BLOCK) {
        const int m = (int)(count - k0 < NEAREST_BLOCK ? count - k0 : NEAREST_BLOCK);
        for (int l = 0; l < m; l++) d[l] = 0;
        for (int j = 0; j < n; j++) {
            const real *x = cols + (size_t)j * (size_t)cap + k0, qj = q[j], Rj = R[j];
#pragma omp simd
            for (int l = 0; l < m; l++) d[l] += Rj * (x[l] > qj ? x[l] - qj : qj - x[l]);
        }
        real lo = (real)INFINITY; /* a NaN distance is never the nearest, as in a scan with < */
        /* min is exact in any order: vectorised from SIMD_REDUCE_LANES nodes on */
        REDUCE_LANES(m, "omp simd reduction(min : lo)", lo = d[l] < lo ? d[l] : lo;);
        if (lo < bd) {
            int l = 0;
            while (d[l] != lo) l++;
            bd = lo, best = k0 + l;
        }
    }
    return best;
}

/* Node k of tree t: its coordinates q (n) into the tree's joint-major columns. */
static inline void DK(plan_put)(DK(PlanWork) *w, int t, int64_t k, const real *q) {
    for (int j = 0; j < w->s.n; j++) w->cols[t][(size_t)j * (size_t)w->cap + k] = q[j];
}

/* Node k of tree t into q (n). */
static inline void DK(plan_node)(const DK(PlanWork) *w, int t, int64_t k, real *q) {
    for (int j = 0; j < w->s.n; j++) q[j] = w->cols[t][(size_t)j * (size_t)w->cap + k];
}

/* Room for nodes up to w->cap_max in both trees: the capacity doubles (a search of many iterations pays for
 * the memory it uses only: 10^6 iterations would be 240 MB per thread up front); 0 when memory ran out, the
 * trees then as they were: the path and parent arrays grow first (larger ones left behind by a later failure
 * are harmless), then both trees' columns are allocated before either moves (their stride is the capacity). */
static int DK(plan_grow)(DK(PlanWork) *w) {
    const int n = w->s.n;
    const int64_t cap = 2 * w->cap < w->cap_max ? 2 * w->cap : w->cap_max;
    if (cap <= w->cap) return 0;
    /* (no path is held in it while the trees grow: it is written before the search and after it) */
    real *path = (real *)realloc(w->path, sizeof(real) * (size_t)(2 * cap * n + 2 * n));
    if (!path) return 0;
    w->path = path;
    for (int t = 0; t < 2; t++) {
        int64_t *parent = (int64_t *)realloc(w->parent[t], sizeof(int64_t) * (size_t)cap);
        if (!parent) return 0;
        w->parent[t] = parent;
    }
    real *cols[2];
    for (int t = 0; t < 2; t++) cols[t] = (real *)malloc(sizeof(real) * (size_t)(cap * n));
    if (!(cols[0] && cols[1])) {
        free(cols[0]), free(cols[1]);
        return 0;
    }
    for (int t = 0; t < 2; t++) {
        for (int j = 0; j < n; j++)
            memcpy(cols[t] + (size_t)j * cap, w->cols[t] + (size_t)j * w->cap, sizeof(real) * w->cap);
        free(w->cols[t]);
        w->cols[t] = cols[t];
    }
    w->cap = cap;
    return 1;
}

/* Room for one more node in a tree of `count` nodes (both trees grown where it has none): 1; 0 where the
 * trees are at w->cap_max (never before max_iterations: it holds every step, DK(plan_search_one)), -1 where
 * memory ran out (the trees as they were: DK(plan_grow)). */
static int DK(plan_room)(DK(PlanWork) *w, int64_t count) {
    if (count < w->cap - 1 || DK(plan_grow)(w)) return 1;
    return w->cap < w->cap_max ? -1 : 0;
}

/* The length sum_j R_j |b_j - a_j| of the edge a -> b in the bound's metric (the search's, in order over j). */
static inline real DK(plan_length)(const real *R, const real *a, const real *b, int n) {
    real L = 0;
    for (int j = 0; j < n; j++) L += R[j] * (b[j] > a[j] ? b[j] - a[j] : a[j] - b[j]);
    return L;
}

/* RRT-Connect's CONNECT: tree t steps from its node k (at qk) towards qn, a node of the other tree, in
 * ceil(L / step) equal steps (L: sum_j R_j |qn_j - qk_j|, at least one step), each step's edge taken whole or
 * not at all and each clear step kept as a node of t (the last one, qn itself, is not: it joins the trees).
 * Returns the node of t that reached qn (the last step's start), -1 where a step collided (or, never, the
 * trees' room w->cap_max was full: it holds every step, DK(plan_search_one)), -2 where memory ran out. */
static int64_t DK(plan_connect)(DK(PlanWork) *w, int t, int64_t k, int64_t *count, const real *qk, const real *qn,
                                real step) {
    const int n = w->s.n;
    const real L = DK(plan_length)((const real *)w->p->reach, qk, qn, n);
    real prior[64], next[64];
    const double r = ceil((double)L / (double)step); /* NaN: one step (then NaN's own verdict) */
    const int64_t ns = L > step ? (r < 0x1p62 ? (int64_t)r : (int64_t)1 << 62) : 1;
    memcpy(prior, qk, sizeof(real) * (size_t)n);
    for (int64_t i = 1; i < ns; i++) {
        const int room = DK(plan_room)(w, count[t]);
        if (room <= 0) return room < 0 ? -2 : -1;
        for (int j = 0; j < n; j++) next[j] = qk[j] + (real)i / (real)ns * (qn[j] - qk[j]);
        if (!DK(plan_edge)(w, prior, next, 1)) return -1;
        const int64_t c = count[t]++;
        DK(plan_put)(w, t, c, next);
        w->parent[t][c] = k;
        k = c;
        memcpy(prior, next, sizeof(real) * (size_t)n);
    }
    return DK(plan_edge)(w, prior, qn, 0) ? k : -1; /* qn: a node, known clear */
}

/* The problem's resolution from its start qs0 and goal qg0 (p->ends >= 1): the largest rung
 * p->resolution / 2^i, i < p->ends, that both clear, found as diffkin.motion.plan._row_resolution finds it
 * (both decided at each rung until each has cleared one; the finer of their two rungs). *bad: 0, or
 * DK_PLAN_START_BAD, DK_PLAN_GOAL_BAD or DK_PLAN_ENDS_BAD where one or both clear no rung. */
static real DK(plan_ends)(DK(PlanWork) *w, const real *qs0, const real *qg0, int64_t *bad) {
    const int n = w->s.n;
    int need[2] = {1, 1};
    real got = (real)w->p->resolution;
    for (int64_t i = 0; i < w->p->ends && (need[0] || need[1]); i++) {
        const double slack = ldexp(w->p->resolution, -(int)i);
        int m = 0, which[2];
        for (int e = 0; e < 2; e++)
            if (need[e]) {
                memcpy(w->qs + m * n, e ? qg0 : qs0, sizeof(real) * (size_t)n);
                which[m++] = e;
            }
        w->cc.slack = slack;
        DK(plan_decide)(w, m, COLLIDE_ALL);
        for (int l = 0; l < m; l++)
            if (w->ok[l]) {
                need[which[l]] = 0;
                got = (real)slack < got ? (real)slack : got;
            }
    }
    *bad = need[0] ? (need[1] ? DK_PLAN_ENDS_BAD : DK_PLAN_START_BAD) : (need[1] ? DK_PLAN_GOAL_BAD : 0);
    return got;
}

static void DK(plan_search_one)(DK(PlanWork) *w, int64_t b);

/* Problem b of w->p: its search (DK(plan_search_one)), its wall time into p->nanoseconds (VAMP's planners
 * time themselves so: from the call's own start and goal to its path). */
static void DK(plan_one)(DK(PlanWork) *w, int64_t b) {
    const int64_t t0 = w->p->nanoseconds ? plan_clock() : 0;
    DK(plan_search_one)(w, b);
    if (w->p->nanoseconds) w->p->nanoseconds[b] = plan_clock() - t0;
}

/* Problem b: its start and goal (with ends), search, shortcut, write its outputs. */
static void DK(plan_search_one)(DK(PlanWork) *w, int64_t b) {
    const dk_plan *p = w->p;
    const int n = w->s.n;
    const int64_t L = p->capacity;
    const real *qs0 = (const real *)p->q_start + b * n, *qg0 = (const real *)p->q_goal + b * n;
    const real *R = (const real *)p->reach, *lo = (const real *)p->lo, *hi = (const real *)p->hi;
    const real step = (real)p->step;
    real *out = (real *)p->path + b * L * n;
    const int64_t wrow = p->world ? p->world[b] : 0;
    for (int l = 0; l < COLLIDE_BLOCK; l++) w->wid[l] = wrow;
    int64_t count[2] = {1, 1}, it = 0, len = 0, status = DK_PLAN_NOT_FOUND, bad = 0;
    w->eta = p->ends > 0 ? DK(plan_ends)(w, qs0, qg0, &bad) : ((const real *)p->eta)[b];
    if (p->ends > 0) ((real *)p->eta)[b] = w->eta;
    w->checked = w->hinted = 0; /* the search's decisions (not the ends') */
    { /* the trees' room: an iteration adds EXTEND's node and at most ceil(D / step) - 1 of CONNECT's steps,
       * D the longest edge between two nodes (the box [lo, hi] with the start and the goal, in the bound's
       * metric), so the trees never fill before max_iterations; allocated only as they grow */
        double D = 0;
        for (int j = 0; j < n; j++) {
            const double l = fmin(fmin((double)lo[j], (double)qs0[j]), (double)qg0[j]);
            const double h = fmax(fmax((double)hi[j], (double)qs0[j]), (double)qg0[j]);
            D += (double)R[j] * (h - l);
        }
        const double k = fmax(1, ceil(D / (double)step)), room = 4 + (double)p->max_iterations * k;
        const int64_t top = (int64_t)1 << 58;
        w->cap_max = room < (double)top ? (int64_t)room : top; /* (NaN: the largest) */
        if (w->cap_max < w->cap) w->cap_max = w->cap; /* (room kept from an earlier problem) */
    }
    w->cc.slack = (double)w->eta;
    DK(plan_forget_hints)(w);
    w->rng = plan_hash(qs0, qg0, sizeof(real) * (size_t)n, p->seed);
    real *path = w->path;
    if (bad) {
        status = bad;
    } else if (DK(plan_edge)(w, qs0, qg0, 1)) { /* the goal decided (or proven by a cover) in the direct
                                             * edge; where that edge is refused, its verdict on the goal
                                             * is not read: the goal is the caller's to pass clear (or
                                             * decided by plan_ends), and later edges take it as clear */
        memcpy(path, qs0, sizeof(real) * n);
        memcpy(path + n, qg0, sizeof(real) * n);
        len = 2;
        status = DK_PLAN_FOUND;
    } else {
        DK(plan_put)(w, 0, 0, qs0);
        DK(plan_put)(w, 1, 0, qg0);
        w->parent[0][0] = w->parent[1][0] = -1;
        real qr[64], qn[64], qa[64], qb[64];
        int64_t join[2] = {-1, -1};
        int64_t it0 = 0;
        for (; it < p->max_iterations; it++) {
            const int room = DK(plan_room)(w, count[0] > count[1] ? count[0] : count[1]);
            if (room <= 0) {
                if (room < 0) status = DK_PLAN_NO_MEMORY;
                break;
            }
            if (p->restart > 0 && it - it0 >= p->restart) { /* a fresh pair of trees, the stream continuing */
                count[0] = count[1] = 1;
                it0 = it;
            }
            const int a = count[1] < count[0]; /* the smaller tree extends (the start's on a tie) */
            if (plan_uniform(&w->rng) < p->goal_bias) {
                DK(plan_node)(w, 1 - a, 0, qr);
            } else {
                for (int j = 0; j < n; j++) qr[j] = lo[j] + (hi[j] - lo[j]) * (real)plan_uniform(&w->rng);
            }
            const int64_t near = DK(plan_nearest)(w->cols[a], w->cap, count[a], qr, R, n);
            DK(plan_node)(w, a, near, qa);
            const real Ld = DK(plan_length)(R, qa, qr, n);
            if (!(Ld > 0)) continue;
            const real f = Ld > step ? step / Ld : 1;
            for (int j = 0; j < n; j++) qn[j] = qa[j] + f * (qr[j] - qa[j]);
            /* EXTEND and each step of CONNECT take a whole edge or nothing (top of this file) */
            if (!DK(plan_edge)(w, qa, qn, 1)) continue; /* qn: a new configuration */
            const int64_t ia = count[a]++;
            DK(plan_put)(w, a, ia, qn);
            w->parent[a][ia] = near;
            const int64_t nb = DK(plan_nearest)(w->cols[1 - a], w->cap, count[1 - a], qn, R, n);
            DK(plan_node)(w, 1 - a, nb, qb);
            const int64_t kb = DK(plan_connect)(w, 1 - a, nb, count, qb, qn, step);
            if (kb == -2) {
                status = DK_PLAN_NO_MEMORY;
                break;
            }
            if (kb >= 0) {
                join[a] = ia;
                join[1 - a] = kb;
                it++;
                break;
            }
        }
        path = w->path; /* moved where the trees grew */
        if (join[0] >= 0) { /* start .. join (tree 0 reversed), then join .. goal (tree 1) */
            int64_t d0 = 0;
            for (int64_t k = join[0]; k >= 0; k = w->parent[0][k]) d0++;
            int64_t k = join[0];
            for (int64_t i = d0 - 1; i >= 0; i--, k = w->parent[0][k])
                DK(plan_node)(w, 0, k, path + i * n);
            len = d0;
            for (k = join[1]; k >= 0; k = w->parent[1][k], len++)
                DK(plan_node)(w, 1, k, path + len * n);
            status = DK_PLAN_FOUND;
        }
    }
    if (status == DK_PLAN_FOUND) { /* random shortcuts: each clear edge i -> j drops the waypoints between */
        /* the pairs found colliding since the path last changed (paths of up to 64 waypoints): a pair drawn
         * again collides again (the same edge, the same decision), so it is not decided again; the draws are
         * unchanged, so the result is the same */
        uint64_t failed[64] = {0};
        for (int64_t t = 0; t < p->shortcut_tries && len > 2; t++) {
            const int64_t i = (int64_t)(plan_uniform(&w->rng) * (double)(len - 2));
            const int64_t j = i + 2 + (int64_t)(plan_uniform(&w->rng) * (double)(len - i - 2));
            if (j >= len) continue;
            const int memo = len <= 64;
            if (memo && (failed[i] >> j & 1)) continue;
            if (!DK(plan_edge)(w, path + i * n, path + j * n, 0)) { /* two waypoints */
                if (memo) failed[i] |= (uint64_t)1 << j;
                continue;
            }
            memmove(path + (i + 1) * n, path + j * n, sizeof(real) * (size_t)((len - j) * n));
            len -= j - i - 1;
            memset(failed, 0, sizeof failed);
        }
        if (len > L) status = DK_PLAN_TOO_LONG;
    }
    if (status != DK_PLAN_FOUND) {
        memcpy(path, qs0, sizeof(real) * n);
        memcpy(path + n, qg0, sizeof(real) * n);
        len = 2;
    }
    memcpy(out, path, sizeof(real) * (size_t)(len * n));
    for (int64_t i = len; i < L; i++) memcpy(out + i * n, qg0, sizeof(real) * n);
    p->n_way[b] = len;
    p->status[b] = status;
    p->iterations[b] = it;
    p->checked[b] = w->checked;
    if (p->hinted) p->hinted[b] = w->hinted;
    if (p->nodes) p->nodes[b] = count[0] + count[1];
}

/* A thread's work space for p (its chain's shape s, plans pp); 0 when memory ran out (then free it). */
static int DK(plan_work_init)(DK(PlanWork) *w, const dk_plan *p, const Shape *s, const DK(Params) *pp) {
    /* the trees' room grows as they fill (DK(plan_grow)), up to each problem's cap_max (DK(plan_search_one)) */
    const int64_t cap = p->max_iterations + 2 < 4096 ? p->max_iterations + 2 : 4096, G = p->C / 2;
    memset(w, 0, sizeof *w);
    w->p = p;
    w->s = *s;
    w->pp = pp;
    w->cap = w->cap_max = cap;
    size_t per;
    w->scratch = DK(team_alloc)(DK(scratch_size)(s) / sizeof(real), 1, &per);
    w->qs = (real *)malloc(sizeof(real) * COLLIDE_BLOCK * (size_t)s->n);
    w->P = (real *)malloc(sizeof(real) * (size_t)p->C * 3 * COLLIDE_BLOCK);
    w->wid = (int64_t *)malloc(sizeof(int64_t) * COLLIDE_BLOCK);
    for (int t = 0; t < 2; t++) {
        w->cols[t] = (real *)malloc(sizeof(real) * (size_t)(cap * s->n));
        w->parent[t] = (int64_t *)malloc(sizeof(int64_t) * (size_t)cap);
    }
    w->path = (real *)malloc(sizeof(real) * (size_t)(2 * cap * s->n + 2 * s->n));
    if (!(w->scratch && w->qs && w->P && w->wid && w->cols[0] && w->cols[1] && w->parent[0] && w->parent[1] &&
          w->path))
        return 0;
    DK(scratch_init)(s, pp, w->scratch, &w->sc);
    w->plain_ends = s->K <= 64;
    for (int k = 0; k < s->K && w->plain_ends; k++) {
        const int e = s->end_joint[k];
        w->plain_ends = !s->has_end[k];
        w->endf[k] = e < 0 ? w->sc.basef : w->sc.F + (size_t)e * 12 * W;
    }
    w->cc = *p->collide;
    DK(plan_forget_hints)(w);
    w->cc.N = COLLIDE_BLOCK; /* DK(plan_rows) sets it for each decision */
    w->cc.A = w->P;
    w->points = 1;
    for (int64_t g = 0; g < G && w->points; g++) {
        const real *hA = (const real *)p->col_h + 4 * g, *hB = (const real *)p->col_h + 4 * (G + g);
        w->points = p->col_frame[g] == p->col_frame[G + g] && hA[0] == hB[0] && hA[1] == hB[1] &&
                    hA[2] == hB[2] && hA[3] == hB[3];
    }
    w->cc.B = w->points ? w->P : w->P + G * 3 * COLLIDE_BLOCK;
    w->cc.wid = w->wid;
    w->cc.nthreads = 1;
    /* a link's geoms move as one: its group (without memory for it, no culling: collide_runs_init) */
    collide_runs_init(&w->runs, G, w->cc.P, w->cc.pi, w->cc.pj, p->col_frame);
    return 1;
}

static void DK(plan_work_free)(DK(PlanWork) *w) {
    free(w->scratch);
    free(w->qs);
    free(w->P);
    free(w->wid);
    for (int t = 0; t < 2; t++) free(w->cols[t]), free(w->parent[t]);
    free(w->path);
    collide_runs_free(&w->runs);
}

static int64_t DK(dk_plan)(const dk_plan *p) {
    Shape s;
    read_shape(p->chain, &s);
    if (s.n > 64) return DK_RANGE_ERROR;
    DK(Params) pp;
    if (DK(read_params)(p->chain, &s, &pp)) return -1;
    int nthreads = plan_threads(p->nthreads, p->B);
    int64_t failed = 0;
#pragma omp parallel num_threads(nthreads) if (nthreads > 1) reduction(+ : failed)
    {
        DK(PlanWork) w;
        const int good = DK(plan_work_init)(&w, p, &s, &pp);
#pragma omp for schedule(dynamic, 1)
        for (int64_t b = 0; b < p->B; b++) {
            if (good) {
                DK(plan_one)(&w, b);
            } else {
                p->status[b] = DK_PLAN_NO_MEMORY;
                p->n_way[b] = 0;
                failed++;
            }
        }
        DK(plan_work_free)(&w);
    }
    free(pp.fix);
    return failed ? -1 : 0;
}

/* dk_plan_decide: p->ok[i] = configuration i of p->q clear (every distance - margin >= p->slack) in world
 * row p->wid[i]; blocks of up to COLLIDE_BLOCK configurations of one world row each, shared between threads. */
static int64_t DK(dk_plan_decide)(const dk_plan *p) {
    Shape s;
    read_shape(p->chain, &s);
    DK(Params) pp;
    if (DK(read_params)(p->chain, &s, &pp)) return -1;
    /* one world row a block: DK(collide_lanes) culls by bounding boxes only where a block's lanes share
     * their world (a block straddling two scenes would test every geom against every object) */
    int64_t *start = (int64_t *)malloc(sizeof(int64_t) * (size_t)(p->N + 2)), nblocks = 0;
    if (!start) {
        free(pp.fix);
        return -1;
    }
    for (int64_t i = 0; i < p->N; i++)
        if (i == 0 || i - start[nblocks - 1] == COLLIDE_BLOCK || (p->wid && p->wid[i] != p->wid[i - 1]))
            start[nblocks++] = i;
    start[nblocks] = p->N;
    int nthreads = plan_threads(p->nthreads, nblocks);
    int64_t failed = 0;
    const int n = s.n;
#pragma omp parallel num_threads(nthreads) if (nthreads > 1) reduction(+ : failed)
    {
        DK(PlanWork) w;
        const int good = DK(plan_work_init)(&w, p, &s, &pp);
        if (good) w.cc.slack = p->slack;
#pragma omp for schedule(dynamic, 4)
        for (int64_t k = 0; k < nblocks; k++) {
            const int64_t n0 = start[k];
            const int m = (int)(start[k + 1] - n0);
            if (!good) {
                failed++;
                continue;
            }
            memcpy(w.qs, (const real *)p->q + n0 * n, sizeof(real) * (size_t)(m * n));
            w.cc.wid = p->wid ? p->wid + n0 : NULL;
            DK(plan_decide)(&w, m, COLLIDE_ALL);
            memcpy(p->ok + n0, w.ok, (size_t)m);
        }
        DK(plan_work_free)(&w);
    }
    free(start);
    free(pp.fix);
    return failed ? -1 : 0;
}

/* dk_plan_edges: the straight edges q[e] -> qb[e] of diffkin.motion._edges.EdgeChecker.edges, each in
 * steps[e] equal sub-steps, its samples 0 .. steps[e] decided by DK(plan_edge_bad) in world row wid[e] with
 * slack slacks[e] (without prefix in COLLIDE_ANY, by covers from 6 sub-steps: only whether the edge is clear
 * is read): first_bad[e] its result (steps + 1: every sample clear), checked[e] the samples decided.
 * Edges are shared between threads. */
static int64_t DK(dk_plan_edges)(const dk_plan *p) {
    Shape s;
    read_shape(p->chain, &s);
    DK(Params) pp;
    if (DK(read_params)(p->chain, &s, &pp)) return -1;
    int nthreads = plan_threads(p->nthreads, p->N);
    int64_t failed = 0;
    const int n = s.n;
#pragma omp parallel num_threads(nthreads) if (nthreads > 1) reduction(+ : failed)
    {
        DK(PlanWork) w;
        const int good = DK(plan_work_init)(&w, p, &s, &pp);
#pragma omp for schedule(dynamic, 8)
        for (int64_t e = 0; e < p->N; e++) {
            if (!good) {
                failed++;
                continue;
            }
            const int64_t row = p->wid ? p->wid[e] : 0;
            for (int l = 0; l < COLLIDE_BLOCK; l++) w.wid[l] = row;
            w.cc.wid = w.wid;
            w.cc.slack = (double)((const real *)p->slacks)[e];
            DK(plan_forget_hints)(&w); /* the sample found: the edge's own, whichever edges the thread had */
            const int64_t before = w.checked;
            p->first_bad[e] = DK(plan_edge_bad)(&w, (const real *)p->q + e * n, (const real *)p->qb + e * n,
                                                p->steps[e], (int)p->prefix, 0, 1,
                                                p->prefix ? COLLIDE_FIRST : COLLIDE_ANY);
            p->checked[e] = w.checked - before;
        }
        DK(plan_work_free)(&w);
    }
    free(pp.fix);
    return failed ? -1 : 0;
}

/* |x - y| (n) in the joint space's Euclidean norm. */
static real DK(plan_dist)(const real *x, const real *y, int n) {
    real ss = 0;
    for (int j = 0; j < n; j++) ss += (x[j] - y[j]) * (x[j] - y[j]);
    return sqrt(ss);
}

/* Path b's shortcuts between points (diffkin.motion._search.shortcut_points, its loop in C): each round
 * `tries` pairs of points drawn uniformly along the path's length from its stream (row_uniform of key, the
 * round), the clear edge between a pair shortening the path the most spliced in; rows past the count hold
 * the last waypoint. The path has room for capacity waypoints (its count + rounds). */
static void DK(plan_points_one)(DK(PlanWork) *w, int64_t b, real *cum, real *seg, real *pts, real *gain,
                                int64_t *seq, int64_t *ij) {
    const dk_plan *p = w->p;
    const int n = w->s.n, T = (int)p->tries;
    const int64_t L = p->capacity;
    real *P = (real *)p->path + b * L * n;
    int64_t cnt = p->n_way[b], misses = 0;
    const int64_t wrow = p->world ? p->world[b] : 0;
    for (int l = 0; l < COLLIDE_BLOCK; l++) w->wid[l] = wrow;
    w->cc.wid = w->wid;
    w->eta = ((const real *)p->eta)[b];
    w->cc.slack = (double)w->eta;
    const uint64_t key = (uint64_t)p->keys[b];
    for (int64_t rnd = 0; rnd < p->rounds && cnt > 2 && misses < p->stop_after; rnd++) {
        cum[0] = 0;
        for (int64_t k = 0; k + 1 < cnt; k++) {
            seg[k] = DK(plan_dist)(P + (k + 1) * n, P + k * n, n);
            cum[k + 1] = cum[k] + seg[k];
        }
        const real total = cum[cnt - 1];
        for (int t = 0; t < T; t++) {
            real tt[2];
            int64_t kk[2];
            for (int e = 0; e < 2; e++) { /* draw 2 t + e of the round: row_uniform(key, rnd, (T, 2)) */
                const uint64_t i = (uint64_t)(2 * t + e) + (uint64_t)rnd * (uint64_t)(2 * T) + 1;
                const uint64_t z = plan_finalise(key + i * 0x9E3779B97F4A7C15ull);
                tt[e] = (real)((double)(z >> 11) * 0x1.0p-53);
            }
            if (tt[1] < tt[0]) { const real x = tt[0]; tt[0] = tt[1]; tt[1] = x; }
            for (int e = 0; e < 2; e++) {
                tt[e] *= total;
                int64_t k = 0; /* the last waypoint at or before the point, within the cnt - 1 segments */
                while (k + 1 < cnt && cum[k + 1] <= tt[e]) k++;
                if (k > cnt - 2) k = cnt - 2;
                kk[e] = k;
                const real ln = seg[k] > DK_TINY ? seg[k] : DK_TINY;
                real f = (tt[e] - cum[k]) / ln;
                f = f < 0 ? 0 : (f > 1 ? 1 : f);
                real *q = pts + (2 * t + e) * n;
                for (int j = 0; j < n; j++) q[j] = P[k * n + j] + f * (P[(k + 1) * n + j] - P[k * n + j]);
            }
            const real g = (tt[1] - tt[0]) - DK(plan_dist)(pts + (2 * t + 1) * n, pts + 2 * t * n, n);
            gain[t] = kk[1] > kk[0] && g > (real)1e-6 * total ? g : -1;
            ij[2 * t] = kk[0], ij[2 * t + 1] = kk[1];
            seq[t] = t;
        }
        for (int a = 1; a < T; a++) /* the tries by gain, largest first (equal gains in draw order) */
            for (int c = a; c > 0 && gain[seq[c]] > gain[seq[c - 1]]; c--) {
                const int64_t x = seq[c]; seq[c] = seq[c - 1]; seq[c - 1] = x;
            }
        int64_t best = -1;
        for (int a = 0; a < T && gain[seq[a]] > 0; a++) {
            const int64_t t = seq[a];
            if (DK(plan_edge_from)(w, pts + 2 * t * n, pts + (2 * t + 1) * n, 0, 1)) { best = t; break; }
        }
        if (best < 0) { misses++; continue; }
        misses = 0;
        const int64_t i = ij[2 * best], j = ij[2 * best + 1], shift = j - i - 2; /* keep 0..i, a, b, j+1.. */
        if (shift > 0)
            for (int64_t c = i + 3; c < cnt - shift; c++) memcpy(P + c * n, P + (c + shift) * n, sizeof(real) * n);
        else if (shift < 0)
            for (int64_t c = cnt - 1 - shift; c >= i + 3; c--) memcpy(P + c * n, P + (c + shift) * n, sizeof(real) * n);
        memcpy(P + (i + 1) * n, pts + 2 * best * n, sizeof(real) * n);
        memcpy(P + (i + 2) * n, pts + (2 * best + 1) * n, sizeof(real) * n);
        cnt -= shift;
    }
    for (int64_t c = cnt; c < L; c++) memcpy(P + c * n, P + (cnt - 1) * n, sizeof(real) * n);
    p->n_way[b] = cnt;
}

/* dk_plan_points: DK(plan_points_one) of the B paths, shared between threads. */
static int64_t DK(dk_plan_points)(const dk_plan *p) {
    Shape s;
    read_shape(p->chain, &s);
    DK(Params) pp;
    if (DK(read_params)(p->chain, &s, &pp)) return -1;
    int nthreads = plan_threads(p->nthreads, p->B);
    int64_t failed = 0;
    const int64_t L = p->capacity, T = p->tries;
#pragma omp parallel num_threads(nthreads) if (nthreads > 1) reduction(+ : failed)
    {
        DK(PlanWork) w;
        const int good = DK(plan_work_init)(&w, p, &s, &pp);
        real *buf = malloc(sizeof(real) * (size_t)(2 * L + 2 * T * s.n + T));
        int64_t *ibuf = malloc(sizeof(int64_t) * (size_t)(3 * T));
#pragma omp for schedule(dynamic, 1)
        for (int64_t b = 0; b < p->B; b++) {
            if (!good || !buf || !ibuf) {
                failed++;
                continue;
            }
            DK(plan_points_one)(&w, b, buf, buf + L, buf + 2 * L, buf + 2 * L + 2 * T * s.n, ibuf, ibuf + T);
        }
        free(buf);
        free(ibuf);
        DK(plan_work_free)(&w);
    }
    free(pp.fix);
    return failed ? -1 : 0;
}

#if DK_PLAN_PASS == 2 /* after the second (float) pass: both types exist */
/* p, its chain and its decisions' struct of this file's versions and sizes, of one real type, with G
 * capsules placed from C = 2 G points. */
static int plan_ok(const dk_plan *p) {
    return DK_LAYOUT_OK(p, dk_plan, DK_PLAN_VERSION) && DK_LAYOUT_OK(p->chain, dk_args, DK_ABI_VERSION) &&
           DK_LAYOUT_OK(p->collide, dk_collide, DK_COLLIDE_VERSION) &&
           p->chain->real_bytes == p->collide->real_bytes && 2 * (p->C / 2) == p->C && p->C / 2 == p->collide->G;
}

/* RRT-Connect and shortcutting of p->B problems (top of this file); returns 0, -1 when memory ran out (those
 * problems' status DK_PLAN_NO_MEMORY), DK_RANGE_ERROR for more than 64 joints, DK_ABI_ERROR for a dk_plan,
 * dk_args or dk_collide of another version or size, or of two real types. */
int64_t dk_plan_search(const dk_plan *p) {
    if (!plan_ok(p)) return DK_ABI_ERROR;
    if (p->chain->real_bytes == 8) return dk_plan_f64(p);
    if (p->chain->real_bytes == 4) return dk_plan_f32(p);
    return DK_ABI_ERROR;
}

/* The decisions of p->N configurations (dk_plan_decide_f64 / _f32 above; p's search fields not read but
 * max_iterations, which sizes the work space: give 0). Returns 0, -1 when memory ran out, DK_ABI_ERROR as
 * dk_plan_search. */
int64_t dk_plan_decide(const dk_plan *p) {
    if (!plan_ok(p)) return DK_ABI_ERROR;
    if (p->chain->real_bytes == 8) return dk_plan_decide_f64(p);
    if (p->chain->real_bytes == 4) return dk_plan_decide_f32(p);
    return DK_ABI_ERROR;
}

/* The edges of p->N straight edges (dk_plan_edges_f64 / _f32 above; p's search fields not read but
 * max_iterations, which sizes the work space: give 0). Returns 0, -1 when memory ran out, DK_RANGE_ERROR
 * for more than 64 joints or an edge of fewer than 1 sub-step, DK_ABI_ERROR as dk_plan_search. */
int64_t dk_plan_edges(const dk_plan *p) {
    if (!plan_ok(p)) return DK_ABI_ERROR;
    if (p->chain->n > 64) return DK_RANGE_ERROR;
    for (int64_t e = 0; e < p->N; e++)
        if (p->steps[e] < 1) return DK_RANGE_ERROR;
    if (p->chain->real_bytes == 8) return dk_plan_edges_f64(p);
    if (p->chain->real_bytes == 4) return dk_plan_edges_f32(p);
    return DK_ABI_ERROR;
}

/* Shortcuts between points of the p->B paths in p->path (B x capacity x n, p->n_way waypoints each,
 * rewritten in place; dk_plan_points_f64 / _f32 above; max_iterations sizes the work space: give 0).
 * Returns 0, -1 when memory ran out, DK_RANGE_ERROR for more than 64 joints, no tries, or a path of fewer
 * than 2 waypoints or without room for one more a round (n_way > capacity - rounds), DK_ABI_ERROR as
 * dk_plan_search. */
int64_t dk_plan_points(const dk_plan *p) {
    if (!plan_ok(p)) return DK_ABI_ERROR;
    if (p->chain->n > 64 || p->tries < 1 || p->rounds < 0) return DK_RANGE_ERROR;
    for (int64_t b = 0; b < p->B; b++)
        if (p->n_way[b] < 2 || p->n_way[b] > p->capacity - p->rounds) return DK_RANGE_ERROR;
    if (p->chain->real_bytes == 8) return dk_plan_points_f64(p);
    if (p->chain->real_bytes == 4) return dk_plan_points_f32(p);
    return DK_ABI_ERROR;
}
#endif
