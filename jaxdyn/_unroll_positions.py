"""Where static indexing moves array elements, in NumPy: XLA's gather, dynamic slices and
scatters applied to arrays of positions (integers) with indices known at trace time, so that
the element-wise evaluation (`jaxdyn._unroll_rules`) renames elements instead of compiling
the primitive once per indexing pattern. Each function follows XLA's operation semantics,
its clamping and its out-of-bounds modes included, and returns None (or, for a scatter,
`NotImplemented`) where it leaves a case to the primitive itself.
"""

import jax
import numpy as np


def clamped_starts(starts, shape, sizes):
    """XLA's clamping of slice starts: into [0, dim − size]."""
    return [int(min(max(int(s), 0), d - z)) for s, d, z in zip(starts, shape, sizes)]


def dynamic_slice_positions(params, operand, *starts):
    sizes = params["slice_sizes"]
    begin = clamped_starts(starts, operand.shape, sizes)
    return operand[tuple(slice(b, b + z) for b, z in zip(begin, sizes))]


def dynamic_update_slice_positions(params, operand, update, *starts):
    begin = clamped_starts(starts, operand.shape, update.shape)
    out = operand.copy()
    out[tuple(slice(b, b + z) for b, z in zip(begin, update.shape))] = update
    return out


def gather_positions(params, operand, indices):
    """XLA's gather (operation semantics, index vector in the last dimension of `indices`),
    element by element; None where a mode other than clamping or in-bounds is asked for."""
    numbers, sizes = params["dimension_numbers"], params["slice_sizes"]
    mode = params["mode"]
    fill = mode == jax.lax.GatherScatterMode.FILL_OR_DROP
    if mode not in (jax.lax.GatherScatterMode.CLIP, jax.lax.GatherScatterMode.PROMISE_IN_BOUNDS,
                    jax.lax.GatherScatterMode.FILL_OR_DROP):
        return None
    offset_dims = numbers.offset_dims
    batch_shape = indices.shape[:-1]
    offset_operand_dims = [d for d in range(operand.ndim)
                           if d not in numbers.collapsed_slice_dims
                           and d not in numbers.operand_batching_dims]
    rank = len(batch_shape) + len(offset_operand_dims)
    batch_dims = [d for d in range(rank) if d not in offset_dims]
    out_shape = [0] * rank
    for d, b in zip(batch_dims, batch_shape):
        out_shape[d] = b
    for d, o in zip(offset_dims, offset_operand_dims):
        out_shape[d] = sizes[o]
    out = np.zeros(out_shape, dtype=operand.dtype)
    for index in np.ndindex(*out_shape):
        batch = tuple(index[d] for d in batch_dims)
        vector = indices[batch]
        start = [0] * operand.ndim
        for k, d in enumerate(numbers.start_index_map):
            start[d] = int(vector[k])
        for d, b in zip(numbers.operand_batching_dims, numbers.start_indices_batching_dims):
            start[d] = batch[b]
        if fill:
            if any(s < 0 or s + z > n for s, z, n in zip(start, sizes, operand.shape)):
                continue  # filled: position 0
        else:
            start = clamped_starts(start, operand.shape, sizes)
        position = list(start)
        for d, o in zip(offset_dims, offset_operand_dims):
            position[o] += index[d]
        out[index] = operand[tuple(position)]
    return out


def scatter_targets(params, operand_shape, indices, updates_shape):
    """{update index: the operand index it lands on, or None where it is dropped} of XLA's
    scatter (index vector in the last dimension of `indices`), or None for a mode or batching
    not handled here."""
    numbers, mode = params["dimension_numbers"], params["mode"]
    modes = jax.lax.GatherScatterMode
    if numbers.operand_batching_dims or mode not in (modes.CLIP, modes.FILL_OR_DROP,
                                                     modes.PROMISE_IN_BOUNDS):
        return None
    window_dims = numbers.update_window_dims
    scatter_dims = [d for d in range(len(updates_shape)) if d not in window_dims]
    operand_window = [d for d in range(len(operand_shape))
                      if d not in numbers.inserted_window_dims]
    sizes = [1] * len(operand_shape)
    for d, w in zip(operand_window, window_dims):
        sizes[d] = updates_shape[w]
    targets = {}
    for index in np.ndindex(*updates_shape):
        vector = indices[tuple(index[d] for d in scatter_dims)]
        start = [0] * len(operand_shape)
        for k, d in enumerate(numbers.scatter_dims_to_operand_dims):
            start[d] = int(vector[k])
        if any(s < 0 or s + z > n for s, z, n in zip(start, sizes, operand_shape)):
            if mode == modes.CLIP:
                start = clamped_starts(start, operand_shape, sizes)
            elif mode == modes.FILL_OR_DROP:  # the whole window is dropped
                targets[index] = None
                continue
            else:  # promised in bounds and not: XLA's own behaviour
                return None
        position = list(start)
        for d, w in zip(operand_window, window_dims):
            position[d] += index[w]
        targets[index] = tuple(position)
    return targets


def scatter_positions(params, operand, indices, updates):
    """XLA's scatter of `updates` into `operand` (the last update to an element wins where
    XLA's order is unspecified: left to XLA, `NotImplemented`)."""
    targets = scatter_targets(params, operand.shape, indices, updates.shape)
    landed = [t for t in (targets or {}).values() if t is not None]
    if targets is None or len(set(landed)) < len(landed):
        return NotImplemented
    out = operand.copy()
    for index, target in targets.items():
        if target is not None:
            out[target] = updates[index]
    return out


POSITIONS = {"gather": gather_positions, "dynamic_slice": dynamic_slice_positions,
             "dynamic_update_slice": dynamic_update_slice_positions,
             "scatter": scatter_positions}
