"""The recursions over a tree of links, and the scans that run them over its levels.

A tree's recursions (Featherstone, Rigid Body Dynamics Algorithms, 2008, ch. 4–7: the links'
poses and velocities outwards from the root, the articulated-body inertias and the forces
inwards from the leaves) take each link after its parent (`forward_split`), or before it
(`backward_split`). For small trees they are a Python loop over the links, straight-line code;
for branched trees of `LEVELS_MIN` links or more a Python loop over the tree's levels, each
level's links together; beyond `LOOP_MAX` links a `lax.scan`, so that compile time does not
grow with the number of links. The scan runs over the links of a chain (the carry is the
parent's state), or over the levels of a branched tree (`_Levels`): the links of one depth
together, each gathering its parent's state from the level above or summing what its
children pass up from the level below, consecutive levels of similar width in one scan
(`_Band`), padded to the band's widest.
These functions know a tree only by its parents' indices; `RigidBodyTree` calls them.
"""
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

# Trees with more links than this run their recursions as a `lax.scan` over links or levels
# (compile time independent of the number of links); smaller ones as a Python loop
# (straight-line code).
LOOP_MAX = 24

# Branched trees of at least this many links (up to `LOOP_MAX`) run their recursions level by
# level in straight-line code (`_forward_by_level`): a quadruped's four legs are three levels
# of four links each, one vectorised step a level instead of twelve one-link steps, which
# makes the program that XLA compiles smaller. ANYmal-C in contact (Tsit5 at 1e-6, 1 s, its
# first `simulate`): the solve's loop 55 724 → 47 234 lines of LLVM IR, the first call about
# 2 s shorter, and about 0.7 s more with its contacts' poses level by level too, the warm run
# unchanged, 1.5–4 % slower in a batch (benchmarks/LOG.md, "ANYmal's first call, level by
# level").
LEVELS_MIN = 12

# Unbranched chains of at least this many links run their recursions in a `lax.scan` (after
# a floating base), at any `LOOP_MAX`: written out, a chain is a level per link and XLA
# compiles a long dependent sequence as one function, for no faster a run. Chains of 16 and
# 20 links, their first `simulate` (Dopri8, 1 s) as a scan against straight-line code: the
# articulated-body algorithm 1.6 / 3.3 s and 1.4 / 4.0 s with runs of 5.0 / 5.7 and
# 6.2 / 6.7 ms; Kane's equations 3.1 / 6.3 s and 4.0 / 8.9 s, runs equal; a vmap of 1024
# states' accelerations 2.9 / 3.1 and 3.6 / 4.0 µs a state (benchmarks/LOG.md, "Chains as
# scans"). Shorter chains' equations are written out as scalar code, where a scan costs more.
CHAIN_LOOP_MIN = 16

# The links' poses alone, a rotation and an offset composed per link, are straight-line code up
# to this many links (level by level in branched trees of `LEVELS_MIN` to `LOOP_MAX` links):
# Talos's 45 cost 1.6 µs per state against 2.1 level by level, its mass matrix 6.2–6.9
# against 7.3–7.8 µs, for 0.7 s more compile (which the articulated-body algorithm,
# compiling in 4.2 s on Talos, does not take: 5.0 s with them).
POSES_LOOP_MAX = 64

# A band of levels costs its levels × its width in link-steps; a further band, about this many
# more (its scans' set-up and the hand-over between bands).
BAND_COST = 6


class _Band:
    """Consecutive levels of a tree taken together in one scan, each padded to the band's
    widest: `slots` (L, W) the link (counted from the head) in each slot, padding slots
    repeating the last link (a leaf, so that a padded slot computes what a real leaf would);
    `parent_slots` (L, W) each slot's parent in the level above, the identity for the band's
    first level, whose parents `entry` (W,) picks from the previous band's last level (in the
    first band: `roots_parents`, the links before the scan or the world); `children`
    (L, W, K) each slot's children in the level below, W where there is none (a row of
    zeros), and for the band's last level, unless it is the tree's, the identity: what its
    children in the next band passed up, `handoff` (W, K) picks and sums before the scan."""

    def __init__(self, levels, slot_of, parents, head, pad, following):
        self.width = width = max(len(level) for level in levels)
        self.slots = np.array([[i - head for i in level] + [pad] * (width - len(level))
                               for level in levels], dtype=np.int32)
        self.entry = np.array([slot_of[parents[i]] if parents[i] >= head else 0
                               for i in levels[0]] + [0] * (width - len(levels[0])),
                              dtype=np.int32)
        self.roots_parents = [parents[i] for i in levels[0]] + [-1] * (width - len(levels[0]))
        self.parent_slots = np.array(
            [list(range(width))] + [[slot_of[parents[i]] for i in level]
                                    + [0] * (width - len(level)) for level in levels[1:]],
            dtype=np.int32)
        below = levels[1:] + ([following] if following else [])
        kids = [[[slot_of[c] for c in level_below if parents[c] == i] for i in level]
                for level, level_below in zip(levels, below)]
        most = max([1] + [len(k) for level in kids for k in level])
        self.children = np.full((len(levels), width, most), width, dtype=np.int32)
        for d, level in enumerate(kids[:len(levels) - (1 if following else 0)]):
            for s, k in enumerate(level):
                self.children[d, s, :len(k)] = k
        self.handoff = np.full((width, most), -1, dtype=np.int32)  # −1: no child
        if following:
            self.children[-1, :, 0] = np.arange(width)
            for s, k in enumerate(kids[-1]):
                self.handoff[s, :len(k)] = k

    def by_slot(self, x):
        """Per-link data (N − head, …) → (L, W, …)."""
        return x[self.slots]


class _Levels:
    """The links of a tree beyond its first `head` taken level by level (their depth below
    the links before them), the levels grouped into bands of consecutive levels (`_Band`) so
    that narrow levels are not padded to the width of the widest: the bands minimise the
    link-steps of the padded levels, plus `BAND_COST` per band (Talos: levels of 3, 3, 5, 5,
    4, 4, 2, 2, 2, 8, 6 links)."""

    def __init__(self, parents, head):
        n = len(parents)
        depth = {}
        for i in range(head, n):
            depth[i] = 0 if parents[i] < head else depth[parents[i]] + 1
        members = [[i for i in range(head, n) if depth[i] == d]
                   for d in range(max(depth.values()) + 1)]
        slot_of = {i: s for level in members for s, i in enumerate(level)}
        # cheapest split of the levels into bands (dynamic programming over the cut points)
        count = len(members)
        best = [0.0] + [np.inf] * count
        cut = [0] * (count + 1)
        for j in range(1, count + 1):
            for i in range(j):
                cost = best[i] + (j - i) * max(len(m) for m in members[i:j]) + BAND_COST
                if cost < best[j]:
                    best[j], cut[j] = cost, i
        edges, j = [], count
        while j:
            edges.append((cut[j], j))
            j = cut[j]
        edges.reverse()
        pad = n - 1 - head
        self.bands = [_Band(members[i:j], slot_of, parents, head, pad,
                            members[j] if j < count else None) for i, j in edges]
        offsets = np.cumsum([0] + [b.slots.size for b in self.bands])
        flat = {}
        for band, offset, (i, j) in zip(self.bands, offsets, edges):
            for d, level in enumerate(members[i:j]):
                for s, link in enumerate(level):
                    flat[link] = offset + d * band.width + s
        self.order = np.array([flat[i] for i in range(head, n)], dtype=np.int32)
        self.num_roots = len(members[0])
        self.members = members
        # where each link's result lies in the levels' results laid end to end
        position = {link: k for k, link in enumerate(i for level in members for i in level)}
        self.level_order = np.array([position[i] for i in range(head, n)], dtype=np.int32)

    def by_link(self, *per_band):
        """The bands' per-slot results (L_b, W_b, …) → (N − head, …) in link order."""
        return jnp.concatenate([x.reshape((-1,) + x.shape[2:]) for x in per_band])[self.order]


@functools.lru_cache(maxsize=64)
def _levels(parents: tuple[int, ...], head: int) -> _Levels:
    """The level structure of a tree (its parents' indices), built once per tree shape: every
    recursion of every trace asks for it."""
    return _Levels(parents, head)


def _stacked(first, rest) -> Any:
    """The states or outputs of a recursion, the head's (a list) and the rest's (stacked, or
    None), stacked over all links."""
    tree_map = jax.tree_util.tree_map
    if not first:
        return rest
    stacked = tree_map(lambda *xs: jnp.stack(xs), *first)
    if rest is None:
        return stacked
    return tree_map(lambda x, y: jnp.concatenate([x.astype(y.dtype), y]), stacked, rest)


def _is_chain(parents) -> bool:
    """Whether every link hangs from the one before it (the first from the world): a chain,
    whose scan carries the parent's state with no level to gather it from."""
    return all(parent == i - 1 for i, parent in enumerate(parents))


def forward_split(parents, step, root, head_links, rest):
    """The parent-to-child recursion over the tree of `parents` (each link's parent's index,
    −1 for the world), with the data of the first links (`RigidBodyTree.scan_head()` of them)
    given one by one (a list: each may have its own shapes, such as a floating base's six
    columns) and the rest's stacked (or None when there is no rest): (state_i, out_i) =
    step(state of parent(i), data_i), the state passed to the children (of the same shape
    for every link of the scan and for the roots it hangs from). Returns the outputs the
    same way, a list and stacked."""
    tree_map = jax.tree_util.tree_map
    n, head = len(parents), len(head_links)
    states, outputs = [], []
    for i in range(head):
        state, out = step(root if parents[i] < 0 else states[parents[i]], head_links[i])
        states.append(state)
        outputs.append(out)
    if head == n:
        return outputs, None
    if _is_chain(parents):  # the carry is the parent's state: no level to gather from
        return outputs, jax.lax.scan(step, states[-1] if states else root, rest)[1]
    # Level by level (links of one depth below the head together, `_Levels`): the carry
    # is the previous level's states, each link's parent gathered from it.
    levels = _levels(parents, head)
    if n <= LOOP_MAX:  # a tree of a few levels: each level's step as straight-line code
        return outputs, _forward_by_level(levels, parents, head, step, root, states, rest)

    def body(previous, xs):
        parent_slot, data = xs
        return jax.vmap(step)(tree_map(lambda x: x[parent_slot], previous), data)

    scanned, last = [], None
    for band in levels.bands:
        if last is None:
            start = tree_map(lambda *xs: jnp.stack(xs), *[
                root if parent < 0 else states[parent] for parent in band.roots_parents])
        else:
            start = tree_map(lambda x: x[band.entry], last)
        last, out = jax.lax.scan(body, start, (band.parent_slots,
                                               tree_map(band.by_slot, rest)))
        scanned.append(out)
    return outputs, tree_map(levels.by_link, *scanned)


def backward_split(parents, step, zero, head_links, rest):
    """The child-to-parent recursion (`RigidBodyTree.backward`) over the tree of `parents`,
    with the data split as in `forward_split`: returns the head's outputs (a list), the
    rest's (stacked, or None) and what the roots passed to the world."""
    tree_map = jax.tree_util.tree_map
    n, head = len(parents), len(head_links)
    accumulated = [zero] * (n + 1)  # the last for the world
    scanned = None
    if head < n:
        if _is_chain(parents):  # the carry is what the child passes up
            def chain_body(carry, data):
                out, up = step(carry, data)
                return tree_map(jnp.add, zero, up), out

            up, scanned = jax.lax.scan(chain_body, zero, rest, reverse=True)
            accumulated[head - 1 if head else n] = up
        elif n <= LOOP_MAX:  # a tree of a few levels: each level's step straight-line code
            scanned, roots = _backward_by_level(_levels(parents, head), parents, head, step,
                                                zero, rest)
            for target, up in roots:
                accumulated[target] = tree_map(jnp.add, accumulated[target], up)
        else:  # level by level, leaves first: the carry is what the level below passes up
            levels = _levels(parents, head)

            def body(below, xs):
                children, data = xs
                total = tree_map(lambda z, s: z[None] + s, zero, _children_sum(below, children))
                out, up = jax.vmap(step)(total, data)
                return up, out

            per_band, up = [None] * len(levels.bands), None
            for b in reversed(range(len(levels.bands))):
                band = levels.bands[b]
                if up is None:  # the tree's last level: nothing below
                    start = tree_map(lambda z: jnp.zeros((band.width,) + jnp.shape(z),
                                                         jnp.result_type(z)), zero)
                else:  # what the next band's first level passed up, summed per parent
                    width_below = jax.tree_util.tree_leaves(up)[0].shape[0]
                    start = _children_sum(up, np.where(band.handoff < 0, width_below,
                                                       band.handoff))
                up, per_band[b] = jax.lax.scan(body, start, (band.children,
                                                             tree_map(band.by_slot, rest)),
                                               reverse=True)
            scanned = tree_map(levels.by_link, *per_band)
            for slot, parent in enumerate(levels.bands[0].roots_parents[:levels.num_roots]):
                target = n if parent < 0 else parent
                accumulated[target] = tree_map(lambda a, x: a + x[slot],
                                               accumulated[target], up)
    outputs = [None] * head
    for i in reversed(range(head)):
        outputs[i], up = step(accumulated[i], head_links[i])
        target = n if parents[i] < 0 else parents[i]
        accumulated[target] = tree_map(jnp.add, accumulated[target], up)
    return outputs, scanned, accumulated[n]


def _children_sum(below, children):
    """Each slot's children's values summed: `children` (W, K) indexes `below` (W', …), with
    W' for no child (a row of zeros)."""
    def summed(b):
        padded = jnp.concatenate([b, jnp.zeros_like(b[:1])])
        # (a scan's band passes its children as data: then a gather)
        return jnp.sum(take(padded, children) if isinstance(children, np.ndarray)
                       else padded[children], axis=1)

    return jax.tree_util.tree_map(summed, below)


def take(x, index):
    """x[index] along the first axis for a static index (a list or NumPy array of any
    shape, whose shape replaces the first axis), as x itself, a slice, or a concatenation of
    slices, one per run of consecutive entries: never a gather, whose derivative in reverse
    mode is a scatter, which XLA's CPU compiler turns into a loop of its own (the costates'
    loop of a two-link tree's optimal control compiled in 16.9 s with them, 10.7 s without)."""
    index = np.asarray(index, dtype=np.int64)
    flat = index.reshape(-1)
    n = len(flat)
    if n == x.shape[0] and np.array_equal(flat, np.arange(n)):
        out = x
    elif n > 1 and flat[1] > flat[0] and np.array_equal(
            flat, flat[0] + (flat[1] - flat[0]) * np.arange(n)):
        out = x[int(flat[0]):int(flat[-1]) + 1:int(flat[1] - flat[0])]
    else:
        breaks = np.flatnonzero(np.diff(flat) != 1) + 1
        runs = np.split(flat, breaks) if n else []
        pieces = [x[int(run[0]):int(run[-1]) + 1] for run in runs]
        out = (pieces[0] if len(pieces) == 1 else jnp.concatenate(pieces)) if pieces \
            else x[:0]
    return out.reshape(index.shape + x.shape[1:])


def _forward_by_level(levels, parents, head, step, root, states, rest):
    """`forward_split`'s outputs for the links beyond the head (stacked, in link order), one
    level at a time in straight-line code: each level's step vectorised over its links, each
    link's parent state taken from the level above (the first level's from the head's
    `states` or the world's `root`)."""
    tree_map = jax.tree_util.tree_map
    outputs, previous, slot_of = [], None, {}
    for level in levels.members:
        data = tree_map(lambda x: take(x, [i - head for i in level]), rest)
        parents_of = [parents[i] for i in level]
        if previous is not None:
            state = tree_map(lambda x: take(x, [slot_of[j] for j in parents_of]), previous)
            previous, out = jax.vmap(step)(state, data)
        elif len(set(parents_of)) == 1:  # (a floating base's legs: one parent, not copied)
            state = root if parents_of[0] < 0 else states[parents_of[0]]
            previous, out = jax.vmap(step, in_axes=(None, 0))(state, data)
        else:
            state = tree_map(lambda *xs: jnp.stack(xs), *[
                root if j < 0 else states[j] for j in parents_of])
            previous, out = jax.vmap(step)(state, data)
        slot_of = {link: s for s, link in enumerate(level)}
        outputs.append(out)
    return tree_map(lambda *xs: take(jnp.concatenate(xs), levels.level_order), *outputs)


def _backward_by_level(levels, parents, head, step, zero, rest):
    """`backward_split`'s outputs for the links beyond the head (stacked, in link order), one
    level at a time from the leaves in straight-line code, and what the first level passes up
    to each of its parents, [(parent, or N for the world, what it receives)]."""
    tree_map = jax.tree_util.tree_map
    members = levels.members
    outputs = [None] * len(members)
    up, below = None, []  # what the level below passed up, and its links
    for d in reversed(range(len(members))):
        level = members[d]
        data = tree_map(lambda x: take(x, [i - head for i in level]), rest)
        if up is None:  # the deepest level: nothing below
            outputs[d], up_here = jax.vmap(step, in_axes=(None, 0))(zero, data)
        else:
            slot_of = {link: s for s, link in enumerate(level)}
            parent_slots = [slot_of[parents[j]] for j in below]
            if parent_slots == list(range(len(level))):  # one child each, in order
                received = up
            else:  # each slot's children's, summed (a slot without children: a row of zeros)
                children = [[k for k, s in enumerate(parent_slots) if s == slot]
                            for slot in range(len(level))]
                most = max(len(c) for c in children)
                index = np.array([c + [len(below)] * (most - len(c)) for c in children])
                received = _children_sum(up, index)
            total = tree_map(lambda z, r: z[None] + r, zero, received)
            outputs[d], up_here = jax.vmap(step)(total, data)
        up, below = up_here, level
    roots = []
    for parent in sorted({parents[i] for i in members[0]}):
        slots = [s for s, i in enumerate(members[0]) if parents[i] == parent]
        roots.append((len(parents) if parent < 0 else parent,
                      tree_map(lambda x: jnp.sum(take(x, slots), axis=0), up)))
    return tree_map(lambda *xs: take(jnp.concatenate(xs), levels.level_order), *outputs), roots
