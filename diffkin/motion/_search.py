"""Batched collision-free path search: straight line first, then RRT-Connect vectorised over problems, then
random shortcutting (between waypoints, then between points anywhere on the path). Every edge goes
through :class:`~diffkin.motion._edges.EdgeChecker` (subdivision with
the proven step bound), all problems' edges of one iteration in one batched decision.

Each problem's two trees (rooted at the start and the goal) are tensors ``(P, 2, C, nq)`` (P: the problems
the straight edge left; room C for min(max_iterations + 2, 4096) nodes, doubled as it fills) with parent
indices; one iteration extends, for every unsolved
problem at once, its tree with fewer nodes (the start's on a tie: balanced trees, as the C search's) by one
step of at most ``step`` (in the bound's metric: metres of geom travel) towards a random configuration when
that whole edge is clear, then CONNECTs the other tree (RRT-Connect's): from its node nearest the new one it
steps towards it in ``ceil(L / step)`` equal steps, keeping each clear step as a node, until a step collides
or the last one reaches the new node and joins the trees. Every edge (EXTEND's, each step of CONNECT) is
taken whole or not at all, as the C search's (``diffkin/kernels/_native_plan.c``).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ._edges import EdgeChecker
from ._native_search import shortcut_points_native

__all__ = ["row_keys", "row_uniform", "search", "shortcut", "shortcut_points"]


def _length(a: Tensor, b: Tensor, w: Tensor) -> Tensor:
    """The length sum_j w_j |b_j - a_j| (...) of the edges a -> b (..., nq) in the weighted L1 metric of the
    bound (w = R: metres of geom travel; the C search's DK(plan_length))."""
    return ((b - a).abs() * w).sum(-1)


def _nearest(nodes: Tensor, count: Tensor, q: Tensor, w: Tensor) -> Tensor:
    """Index (B,) of the node of each tree (B, C, nq) (first ``count`` valid) nearest to q (B, nq), in the
    weighted L1 metric of the bound (w = R)."""
    d = _length(q[:, None], nodes, w)
    C = nodes.shape[1]
    d = torch.where(torch.arange(C, device=q.device)[None] < count[:, None], d, torch.inf)
    return d.argmin(1)


_ROOM = 4096  # each tree's first room for nodes (search)


def _room(nodes: Tensor, parent: Tensor, slot: Tensor) -> tuple[Tensor, Tensor]:
    """The trees (P, 2, C, nq) and their parents (P, 2, C), their room doubled where a node is about to go
    into a slot past it (``slot``: the next free slot of each tree taking one)."""
    if int(slot.max()) < nodes.shape[2]:
        return nodes, parent
    return torch.cat((nodes, torch.zeros_like(nodes)), 2), torch.cat((parent, torch.full_like(parent, -1)), 2)


def _trace(nodes: Tensor, parent: Tensor, leaf: Tensor) -> tuple[Tensor, Tensor]:
    """Root-to-leaf paths (B, D, nq) (the root is node 0), padded at the end with the leaf, and their
    waypoint counts (B,)."""
    B = nodes.shape[0]
    rows = torch.arange(B, device=nodes.device)
    walk, cur = [leaf], leaf
    while True:
        p = parent[rows, cur]
        if bool((p < 0).all()):
            break
        cur = torch.where(p < 0, cur, p)  # a row at its root stays there
        walk.append(cur)
    idx = torch.stack(walk[::-1], 1)  # (B, D): the root repeated in front of the shallower rows
    D = idx.shape[1]
    roots = (idx == 0).sum(1)  # node 0 appears once on a path: the repeats are the padding
    depth = D - roots + 1
    shift = (torch.arange(D, device=nodes.device)[None] + (roots - 1)[:, None]).clamp(max=D - 1)
    return nodes[rows[:, None], torch.gather(idx, 1, shift)], depth


def search(checker: EdgeChecker, q_start: Tensor, q_goal: Tensor, lo: Tensor, hi: Tensor, problem: Tensor, *,
           max_iterations: int, step: float, generator: torch.Generator,
           goal_bias: float = 0.0) -> tuple[Tensor, Tensor, Tensor]:
    """Paths (B, L, nq) from q_start to q_goal (B, nq) of problems ``problem (B,)`` (the rows' scenes in the
    checker's world; rows padded with the goal), their waypoint counts (B,) and ``found (B,)``. Start and
    goal must already be clear (rows where they are not stay unfound). With probability ``goal_bias`` a
    tree extends towards the other tree's root instead of a uniform sample."""
    B, nq = q_start.shape
    dev, dt = q_start.device, q_start.dtype
    w = checker.reach.to(dt)
    free, _ = checker.edges(q_start, q_goal, problem)
    found = free.clone()
    paths = [torch.stack((q_start, q_goal), 1)]
    lengths = torch.full((B,), 2, dtype=torch.long, device=dev)
    todo = (~found).nonzero().squeeze(1)
    if todo.numel() == 0 or max_iterations == 0:
        return paths[0], lengths, found
    C = min(max_iterations + 2, _ROOM)  # node room per tree, doubled as CONNECT's steps fill it (_room)
    nb = todo.numel()
    pid = problem[todo]  # the problem of each tree pair
    # the two trees of each problem: 0 rooted at the start, 1 at the goal
    nodes = q_start.new_zeros(nb, 2, C, nq)
    nodes[:, 0, 0], nodes[:, 1, 0] = q_start[todo], q_goal[todo]
    parent = torch.full((nb, 2, C), -1, dtype=torch.long, device=dev)
    count = torch.ones(nb, 2, dtype=torch.long, device=dev)
    active = torch.ones(nb, dtype=torch.bool, device=dev)
    link = torch.zeros(nb, 2, dtype=torch.long, device=dev)  # (node in tree 0, node in tree 1) at the join
    for _ in range(max_iterations):
        rows = active.nonzero().squeeze(1)
        if rows.numel() == 0:
            break
        ta = (count[rows, 1] < count[rows, 0]).long()  # the smaller tree extends (the start's on a tie)
        tb = 1 - ta
        r = len(rows)
        q_rand = lo + (hi - lo) * torch.rand(r, nq, generator=generator, dtype=dt, device="cpu").to(dev)
        if goal_bias > 0:
            u = torch.rand(r, generator=generator, dtype=torch.float64, device="cpu")  # the batch's stream
            towards = u.to(dev) < goal_bias
            q_rand = torch.where(towards[:, None], nodes[rows, tb, 0], q_rand)
        near = _nearest(nodes[rows, ta], count[rows, ta], q_rand, w)
        q_near = nodes[rows, ta, near]
        d = q_rand - q_near
        L = _length(q_near, q_rand, w)
        q_new = q_near + d * (step / L.clamp(min=step))[:, None]
        # EXTEND by the whole edge or not at all (as the C search: a rejected edge is usually caught by its
        # coarse samples)
        ok, _ = checker.edges(q_near, q_new, pid[rows])
        grow, ga, gb = rows[ok], ta[ok], tb[ok]
        if grow.numel():
            slot = count[grow, ga]
            nodes, parent = _room(nodes, parent, slot)
            nodes[grow, ga, slot] = q_new[ok]
            parent[grow, ga, slot] = near[ok]
            count[grow, ga] += 1
            # CONNECT: the other tree steps from its nearest node towards the new one (module docstring)
            qn = q_new[ok]
            cur = _nearest(nodes[grow, gb], count[grow, gb], qn, w)
            qk = nodes[grow, gb, cur]
            ns = _length(qk, qn, w).div(step).ceil().clamp(min=1)
            ns = torch.nan_to_num(ns, nan=1.0, posinf=1.0)  # (not finite: one step, its edge's own verdict)
            prior, on, i = qk, torch.arange(len(grow), device=dev), 1  # on: the rows still stepping
            while on.numel():
                g, b = grow[on], gb[on]
                last = ns[on] <= i
                nxt = torch.where(last[:, None], qn[on], qk[on] + (i / ns[on])[:, None] * (qn[on] - qk[on]))
                clear, _ = checker.edges(prior, nxt, pid[g])
                done = clear & last
                if bool(done.any()):
                    link[g[done], ga[on][done]] = slot[on][done]
                    link[g[done], b[done]] = cur[on][done]
                    active[g[done]] = False
                keep = clear & ~last
                on, g, b, nxt = on[keep], g[keep], b[keep], nxt[keep]
                if on.numel():
                    c = count[g, b]
                    nodes, parent = _room(nodes, parent, c)
                    nodes[g, b, c] = nxt
                    parent[g, b, c] = cur[on]
                    count[g, b] += 1
                    cur[on] = c
                prior, i = nxt, i + 1
    joined = ~active
    sub_found = joined
    p0, n0 = _trace(nodes[:, 0], parent[:, 0], link[:, 0])
    p1, n1 = _trace(nodes[:, 1], parent[:, 1], link[:, 1])
    # start … join (tree 0, root first) then join … goal (tree 1 reversed)
    D0, D1 = p0.shape[1], p1.shape[1]
    Lmax = D0 + D1
    i = torch.arange(Lmax, device=dev)[None]
    from0 = i < n0[:, None]
    j1 = (n0[:, None] + n1[:, None] - 1 - i).clamp(0, D1 - 1)  # tree 1's path is root(goal)-first
    take0 = torch.gather(p0, 1, i.clamp(max=D0 - 1)[..., None].expand(nb, Lmax, nq))
    out = torch.where(from0[..., None], take0, torch.gather(p1, 1, j1[..., None].expand(nb, Lmax, nq)))
    n = n0 + n1
    out = torch.where((i < n[:, None])[..., None], out, q_goal[todo][:, None])
    full = q_goal[:, None].expand(B, Lmax, nq).clone()
    full[:, 0] = q_start
    full[todo] = out
    lengths[todo] = torch.where(sub_found, n, 2)
    found[todo] = sub_found
    return full, lengths, found


def shortcut(checker: EdgeChecker, path: Tensor, n: Tensor, problem: Tensor, rounds: int,
             generator: torch.Generator, tries: int = 4) -> tuple[Tensor, Tensor]:
    """Random shortcutting of paths (B, L, nq) with n (B,) waypoints of problems ``problem (B,)``: each
    round, every path tries ``tries``
    straight edges between random waypoints i < j − 1 (all in one batched decision) and, of the clear ones,
    takes the one dropping the most waypoints."""
    B, L, nq = path.shape
    dev = path.device
    rows = torch.arange(B, device=dev)
    cols = torch.arange(L, device=dev)[None]
    for _ in range(rounds):
        can = (n > 2).nonzero().squeeze(1)
        if can.numel() == 0:
            break
        m = n[can, None]
        u = torch.rand(can.numel(), tries, 2, generator=generator, dtype=torch.float64, device="cpu").to(dev)
        i = (u[..., 0] * (m - 2)).long().clamp(max=m - 3)  # 0 <= i <= n - 3
        j = i + 2 + (u[..., 1] * (m - i - 2)).long().clamp(max=m - i - 3)  # i + 2 <= j <= n - 1
        r = can[:, None].expand(-1, tries)
        free, _ = checker.edges(path[r, i].reshape(-1, nq), path[r, j].reshape(-1, nq),
                                problem[r].reshape(-1))
        gain = torch.where(free.view(-1, tries), j - i - 1, 0)
        best = gain.argmax(1)
        drop = torch.zeros(B, dtype=torch.long, device=dev)
        ii = torch.zeros(B, dtype=torch.long, device=dev)
        drop[can] = gain[torch.arange(can.numel(), device=dev), best]
        ii[can] = i[torch.arange(can.numel(), device=dev), best]
        src = torch.where(cols > ii[:, None], cols + drop[:, None], cols).clamp(max=L - 1)
        path = path[rows[:, None], src]
        n = n - drop
    return path, n


def _signed(c: int) -> int:
    return c - (1 << 64) if c >= 1 << 63 else c


#: splitmix64's constants as unsigned 64-bit integers, and as the int64 values of the same bits
_MASK = (1 << 64) - 1
_GOLDEN_U, _M1_U, _M2_U = 0x9E3779B97F4A7C15, 0xBF58476D1CE4E5B9, 0x94D049BB133111EB
_GOLDEN, _M1, _M2 = _signed(_GOLDEN_U), _signed(_M1_U), _signed(_M2_U)


def _mix(x):
    """splitmix64's finaliser on int64 tensors or numpy arrays (wrapping products; the shifts logical, by
    masking)."""
    shr = lambda v, k: (v >> k) & ((1 << (64 - k)) - 1)  # noqa: E731
    x = (x ^ shr(x, 30)) * _M1
    x = (x ^ shr(x, 27)) * _M2
    return x ^ shr(x, 31)


def _mix_uint(x: int) -> int:
    """:func:`_mix` on a Python integer in [0, 2^64) (the products reduced modulo 2^64)."""
    x = ((x ^ (x >> 30)) * _M1_U) & _MASK
    x = ((x ^ (x >> 27)) * _M2_U) & _MASK
    return x ^ (x >> 31)


#: batches of at most this many rows get their :func:`row_keys` in Python integers on the CPU (numpy's
#: 2 nq rounds of whole-array operations cost ~0.5 ms whatever the batch)
_INT_ROWS = 8


def row_keys(q_start: Tensor, q_goal: Tensor, seed: int) -> Tensor:
    """(B,) int64: a random-stream key per problem from ``seed`` and the bits of its start and goal, so
    that a problem's draws (:func:`row_uniform`) do not depend on the batch it is planned in (as the C
    search's streams). ``seed`` fits an int64 (plan checks it)."""
    bits = torch.cat((q_start, q_goal), -1).detach().to(torch.float64).contiguous().view(torch.int64)
    if bits.device.type == "cpu" and bits.shape[0] <= _INT_ROWS:  # Python integers: 14 µs a row, not 460
        keys = []
        for row in bits.tolist():
            key = seed & _MASK
            for col in row:
                key = _mix_uint(key ^ ((col + _GOLDEN_U) & _MASK))
            keys.append(_signed(key))
        return torch.tensor(keys, dtype=torch.int64, device=bits.device)  # never the default device
    key = torch.full(bits.shape[:1], seed, dtype=torch.int64, device=bits.device)
    cols = bits.T
    if bits.device.type == "cpu":  # in numpy (the same int64 wrapping): 2 nq rounds of torch ops cost ~1-2 ms
        key, cols = key.numpy(), cols.numpy()
    for col in cols:
        key = _mix(key ^ col + _GOLDEN)
    return torch.as_tensor(key, device=bits.device)  # never the default device (a numpy key: the CPU)


def row_uniform(key: Tensor, counter: int, shape: tuple[int, ...]) -> Tensor:
    """(B, *shape) float64 uniform in [0, 1): draw ``counter`` of the streams ``key`` (B,)."""
    k = 1
    for d in shape:
        k *= d
    i = torch.arange(k, dtype=torch.int64, device=key.device) + counter * k + 1
    z = _mix(key[:, None] + i * _GOLDEN)
    return ((z >> 11) & ((1 << 53) - 1)).to(torch.float64).mul_(2.0 ** -53).view(key.shape[0], *shape)


#: :func:`shortcut_points` stops trying on a path after this many rounds in a row found no clear shortcut
STOP_AFTER = 4


def shortcut_points(checker: EdgeChecker, path: Tensor, n: Tensor, problem: Tensor, rounds: int,
                    key: Tensor, tries: int = 8) -> tuple[Tensor, Tensor]:
    """Random shortcutting between points anywhere on the paths (B, L, nq) with n (B,) waypoints of problems
    ``problem (B,)``, not only between waypoints (which leaves the detours of a path with few waypoints):
    each round every path tries ``tries`` straight edges a → b between two points drawn uniformly along its
    joint-space length (each path's own stream ``key`` (B,), :func:`row_keys`), on different segments
    i < j, and of the clear ones takes the one shortening the path the most (checked best first: a path's
    next try only where its better ones collide; each check one batched decision):
    ``w_0 … w_i, a, b, w_(j+1) … w_(n−1)``. The pieces ``w_i → a`` and ``b → w_(j+1)`` are parts of edges
    already proven clear, so the path stays proven. A path stops after :data:`STOP_AFTER` rounds in a row
    without a clear shortcut. Returns the paths (B, L', nq) (L' ≤ L + rounds; rows padded with their last
    waypoint) and their counts. Where the checker decides in C (CPU, the C decisions serve its model and
    world, ``checker.use_c``), the rounds run in C (:func:`~diffkin.motion._native_search.
    shortcut_points_native`: the same choices, the points to rounding; rows of ``L + rounds``)."""
    got = shortcut_points_native(checker, path, n, problem, rounds, key, tries, STOP_AFTER)
    if got is not None:
        return got
    B, L, nq = path.shape
    dev = path.device
    misses = torch.zeros(B, dtype=torch.long, device=dev)
    for rnd in range(rounds):
        can = ((n > 2) & (misses < STOP_AFTER)).nonzero().squeeze(1)
        if can.numel() == 0:
            break
        cols = torch.arange(L, device=dev)[None]
        p = path[can]
        seg = (p[:, 1:] - p[:, :-1]).norm(dim=-1)
        seg = torch.where(cols[:, :-1] < (n[can] - 1)[:, None], seg, 0.0)
        cum = torch.cat((seg.new_zeros(can.numel(), 1), seg.cumsum(1)), 1)  # (C, L)
        total = cum[:, -1:]
        u = row_uniform(key[can], rnd, (tries, 2)).to(path.dtype)
        t = u.sort(-1).values * total[..., None]  # (C, tries, 2)
        # the segment holding each point: the last waypoint at or before it (within the row's n − 1 segments)
        k = (torch.searchsorted(cum, t.reshape(can.numel(), -1), right=True) - 1).view_as(t)
        k = torch.minimum(k.clamp(min=0), (n[can] - 2)[:, None, None])
        base = torch.gather(cum, 1, k.flatten(1)).view_as(t)
        ln = torch.gather(seg, 1, k.flatten(1)).view_as(t)
        f = ((t - base) / ln.clamp(min=torch.finfo(path.dtype).tiny)).clamp(0, 1)
        r = torch.arange(can.numel(), device=dev)[:, None, None]
        pt = p[r, k] + f[..., None] * (p[r, k + 1] - p[r, k])  # (C, tries, 2, nq)
        a, b = pt[:, :, 0], pt[:, :, 1]
        i, j = k[..., 0], k[..., 1]
        direct = (b - a).norm(dim=-1)
        gain = (t[..., 1] - t[..., 0]) - direct
        # shortcuts within one segment change nothing; tiny ones are not worth an edge check
        gain = torch.where((j > i) & (gain > 1e-6 * total), gain, -1.0)
        # the tries by gain, largest first, in stages of 1, 2 and the rest: a path's tries of a stage checked
        # (one batched decision) only where all its better ones collided, the best clear one of the first
        # stage holding one taken (the same choice as one try at a time, best first: a clear edge costs all
        # its subdivision samples, a colliding one usually few; one decision per try cost more in calls)
        order = gain.argsort(1, descending=True)
        c = torch.arange(can.numel(), device=dev)
        best = torch.full_like(c, -1)
        for lo, hi in ((0, 1), (1, 3), (3, tries)):
            if lo >= tries:
                break
            o = order[:, lo:hi]  # (C, s)
            rows, col = ((best < 0)[:, None] & (gain.gather(1, o) > 0)).nonzero(as_tuple=True)
            if rows.numel() == 0:
                break
            tried = o[rows, col]
            free, _ = checker.edges(a[rows, tried], b[rows, tried], problem[can[rows]])
            # per path its first clear try of the stage (in gain order): the smallest stage column
            hit = torch.full((can.numel(), hi - lo), hi - lo, dtype=torch.long, device=dev)
            hit[rows[free], col[free]] = col[free]
            first = hit.min(1).values
            won = first < hi - lo
            best[won] = o[won, first[won]]
        take = best >= 0
        misses[can] = torch.where(take, 0, misses[can] + 1)
        if not bool(take.any()):
            continue
        ct, bi = c[take], best[take]
        tr = can[take]
        i, j = i[ct, bi], j[ct, bi]
        a, b = a[ct, bi], b[ct, bi]
        new_n = n.clone()
        new_n[tr] = n[tr] + 2 - (j - i)  # i + 1 kept, a and b, n − 1 − j kept after them
        L2 = max(L, int(new_n.max()))
        if L2 > L:
            path = torch.cat((path, path[:, -1:].expand(B, L2 - L, nq)), 1)
            L = L2
        cols = torch.arange(L, device=dev)[None]
        src = torch.where(cols > i[:, None] + 2, cols + (j - i - 2)[:, None], cols).clamp(max=L - 1)
        sub = path[tr[:, None], src]
        sub[torch.arange(tr.numel(), device=dev), i + 1] = a
        sub[torch.arange(tr.numel(), device=dev), i + 2] = b
        # past the row's last waypoint: its goal
        last = path[tr, n[tr] - 1]
        sub = torch.where((cols < new_n[tr][:, None])[..., None], sub, last[:, None])
        path = path.clone()
        path[tr] = sub
        n = new_n
    return path, n
