"""`simulate_batch`: one system simulated from many initial states or parameter sets, sharded
over the devices present (one or many hosts) and run in chunks of bounded size."""

import inspect
import math

import diffrax
import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
import tqdm
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ._compile import FUSION_EMITTERS, batch_emitters, filter_jit, gc_paused
from ._dynamics import AbstractDynamics, straight_line_size
from ._errors import error_if, reports_state
from ._integrate import simulate
from ._solution import RESULTS, Solution
from ._state import numbers_as_arrays, state_dtype

_BATCH = PartitionSpec("batch")
# Every failure code (equinox enumerations list their members only in `_name_to_item`).
_FAILURES = [item for item in RESULTS._name_to_item.values() if item is not RESULTS.successful]
# Members per device are padded to a multiple of LANES: XLA computes a vmapped solve on a CPU
# in SIMD vectors of 4 (AVX2) or 8 (AVX-512) float64 members, and a member left over after the
# full vectors is computed by other (scalar) code that differs in the last bits, which an
# adaptive solve can amplify. In full vectors every member's result is the same, bit for bit,
# whatever the layout of the batch.
LANES = 8
PILOT_TOLERANCE = {8: 1e-6, 4: 1e-4}  # by bytes per float: the pilot of order="cost"
_NUMBERS = ("t0", "t1", "ts", "rtol", "atol", "dt0")  # traced: changing them reuses the compile
_OPTIONS = frozenset(inspect.signature(simulate).parameters) - {"dynamics", "q0", "u0", "p",
                                                                "throw"}


@reports_state
def simulate_batch(
    dynamics,
    q0,
    u0,
    p=None,
    *,
    batched_params=False,
    chunk_size: int | None = None,
    max_bytes: int | None = None,
    devices=None,
    order: str = "given",
    progress: bool = False,
    throw: bool = True,
    **options,
) -> Solution:
    """Simulate a batch: member i starts at (q0[i], u0[i]) with parameters p[i].

    The members are sharded over `devices` along one mesh axis (`jax.sharding.Mesh`,
    `jax.shard_map`): each device integrates its share of the members as one vmapped solve,
    independently of the others (an adaptive solve on one device does not wait, step by step,
    for the slowest member on another). The batch is padded with copies of its last member to
    whole chunks of a multiple of 8 members per device (once it has 8 per device), and the
    padding is stripped from the result: every member then fills a lane of XLA's vector code,
    so that its result does not depend on the layout of the batch (devices, chunks, position),
    to the last bit on regular motion; on chaotic motion XLA's vectorisation of the
    Runge–Kutta stages can differ by an ulp between chunk shapes, which the motion
    amplifies (2e-12 after 5 s of a chaotic double pendulum), as it amplifies the difference
    between a batch and single `jaxdyn.simulate` calls (scalar code).
    Batches larger than memory run in chunks, one compiled solve reused for every chunk, each
    chunk's results moved to host memory before the next starts. Each device runs the program
    of `jax.vmap(simulate)` on its members. On a CPU it compiles that program with XLA's
    fusion emitters when the equations are small (at most 800 scalar operations as
    straight-line code; they vectorise the solver's loop over the members better) and with
    the process's default otherwise, so that its results equal those of a user's
    `jax.jit(jax.vmap(simulate))` to the last bits, which chaotic motion amplifies.

    **Arguments:**

    - `dynamics`, `p`, and every keyword of `jaxdyn.simulate` (`t1`, `ts`, `solver`, `rtol`,
      `save`, ...) as for one simulation; they are shared by all members.
    - `q0`, `u0`: (B, n) and (B, m) for a batch of initial states, or (n,) and (m,) for one
      initial state shared by every member.
    - `batched_params`: which leaves of `p` carry a leading batch axis: False (none: the
      parameters are shared), True (all), or a pytree prefix of `p` of bools, as an equinox
      filter (e.g. `{"k": True, "g": False}`). All batched leading axes must agree.
    - `chunk_size`: at most this many members in device memory at once; or `max_bytes`: at
      most this many bytes of results (the saved trajectories and, with `dense=True`, the
      interpolants; a member's working state during the solve is a few copies of its state,
      small beside them) per chunk. Either is rounded down to a multiple of 8 members per
      device (at least 8 per device, for batches that large; see above). Neither: one chunk.
    - `devices`: the devices to shard over; default `jax.devices()`, every device of every
      process (after `jax.distributed.initialize` in a multi-host run; every process then calls
      `simulate_batch` with the same arguments and receives the whole result). On a CPU, JAX
      shows one device unless `XLA_FLAGS=--xla_force_host_platform_device_count=N` is set
      before JAX starts: set N to the number of cores to use them all.
    - `order`: "given" runs the members in the order given; "cost" first runs a cheap pilot
      solve (Tsit5 at rtol = atol = 1e-6, 1e-4 in float32, final state only) to count each
      member's steps and runs members of similar cost together, so that a chunk or device of regular
      members does not wait for a chaotic one; the result is in the order given. It pays with
      several chunks or devices and mixed costs (benchmarks/LOG.md).
    - `progress`: a tqdm progress bar over the chunks.
    - `throw`: with True, a failing member raises a `RuntimeError` naming its index, its
      initial state and parameters, and jaxdyn's message for the failure (the time and state
      where it happened, from a re-run of that member alone). With False, every member carries
      its own `result` code and the others are unaffected; a member whose initial state or
      parameters hold NaN or inf gets NaN results and `RESULTS.nonfinite_state_or_parameters`
      (as from `jaxdyn.simulate` with throw=False).

    **Returns:** one `jaxdyn.Solution` whose every field has a leading batch axis of size B.
    Its arrays are JAX arrays with one chunk in one process, NumPy arrays in host memory
    otherwise. The results are those of an unsharded `jax.vmap(jaxdyn.simulate)` over the same
    members (tested to 1e-12 on 1 and 4 devices and in 2 processes, and against single
    simulations and closed forms).

    Called inside `jax.jit` or a transformation (`jax.grad` through a batch), it stages the same
    sharded solve; chunks become a `jax.lax.map` over chunks (bounding the solver's working
    memory, not that of the results, which stay on the device), and `throw=True` reports the
    first failing member's index and initial state.
    """
    inputs = options.pop("inputs", None)
    if inputs is not None:  # shared by the members (a policy sees each member's state)
        dynamics = dynamics.with_inputs(inputs)
    _check_options(options, order)
    dtype = state_dtype(q0, u0)
    if isinstance(dynamics, AbstractDynamics):  # (a Contact scene appends its deformations)
        q0 = dynamics.initial_coordinates(jnp.asarray(q0, dtype), jnp.asarray(u0, dtype), p)
    batched, shared, numbers = _split_members(q0, u0, p, batched_params, options, dtype)
    size = _batch_size(batched)
    mesh = Mesh(np.asarray(jax.devices() if devices is None else list(devices)), ("batch",))
    chunk = _chunk_size(size, mesh.devices.size, chunk_size, max_bytes, dynamics, batched,
                        shared, options)
    setup = (dynamics, mesh, tuple(sorted(options.items())))
    if any(isinstance(x, jax.core.Tracer)
           for x in jax.tree_util.tree_leaves((dynamics, batched, shared))):
        return _staged(setup, batched, shared, size, chunk, throw)
    permutation = None
    if order == "cost":
        permutation = _by_cost(dynamics, q0, u0, p, batched_params, chunk, devices, numbers,
                               options, dtype)
        batched = jax.tree_util.tree_map(lambda x: np.asarray(x)[permutation], batched)
    emitters = _emitters(dynamics, batched, shared, mesh, dtype)
    solution = _solve_in_chunks(setup, batched, shared, size, chunk, progress, throw,
                                permutation, emitters)
    if permutation is not None:
        solution = jax.tree_util.tree_map(lambda x: x[np.argsort(permutation)], solution)
    return solution


def _check_options(options, order):
    unknown = set(options) - _OPTIONS
    if unknown:
        raise ValueError(f"simulate_batch got unknown keyword(s) {sorted(unknown)}; it takes "
                         f"jaxdyn.simulate's: {sorted(_OPTIONS)}.")
    if "t1" not in options:
        raise TypeError("simulate_batch() missing the keyword argument 't1' (the end time).")
    if order not in ("given", "cost"):
        raise ValueError(f"order must be 'given' or 'cost', got {order!r}.")


def _split_members(q0, u0, p, batched_params, options, dtype):
    """(batched, shared, numbers): the inputs with a leading batch axis, those shared by every
    member (with the numbers of `options`, which are taken out of it, as arrays), and those
    numbers as given."""
    q0, u0 = (x if isinstance(x, jax.core.Tracer) else np.asarray(x, dtype) for x in (q0, u0))
    for name, x in (("q0", q0), ("u0", u0)):
        if x.ndim not in (1, 2):
            raise ValueError(f"{name} must have shape (B, n) for a batch of states, or (n,) for "
                             f"one shared state; got shape {x.shape}.")
    spec = (q0.ndim == 2, u0.ndim == 2, batched_params)
    try:
        batched, shared = eqx.partition((q0, u0, p), spec, is_leaf=lambda x: x is None)
    except ValueError as error:
        raise ValueError("batched_params must be True, False or a pytree prefix of p with "
                         f"bool leaves: {error}") from None
    numbers = {k: options.pop(k) for k in _NUMBERS if k in options}
    return batched, numbers_as_arrays((shared, numbers), dtype), numbers


def _by_cost(dynamics, q0, u0, p, batched_params, chunk, devices, numbers, options, dtype):
    """The members ordered by cost: a pilot solve at a loose tolerance counts their steps."""
    pilot = simulate_batch(dynamics, q0, u0, p, batched_params=batched_params,
                           chunk_size=chunk, devices=devices, throw=False, save="q",
                           t0=numbers.get("t0", 0.0), t1=numbers["t1"],
                           solver=diffrax.Tsit5(), rtol=PILOT_TOLERANCE[dtype.itemsize],
                           atol=PILOT_TOLERANCE[dtype.itemsize],
                           max_steps=options.get("max_steps", 16**4))
    return np.argsort(np.asarray(pilot.num_steps), kind="stable")


def _solve_in_chunks(setup, batched, shared, size, chunk, progress, throw, permutation,
                     emitters):
    """The sharded solve of every chunk of members, gathered (in host memory when there are
    several chunks or hosts), each chunk's failures reported as it finishes."""
    dynamics, mesh, options = setup[0], setup[1], dict(setup[2])
    count = math.ceil(size / chunk)
    padded = _pad(batched, count * chunk)
    solve_chunk = _SOLVE_CHUNK["events" if options.get("events") is not None else emitters]
    in_host = count > 1 or jax.process_count() > 1
    solution = None
    bar = tqdm.tqdm(total=count, disable=not progress, unit="chunk", desc="simulate_batch")
    try:
        for k in range(count):
            members = jax.tree_util.tree_map(lambda x: x[k * chunk:(k + 1) * chunk], padded)
            with gc_paused():  # the first chunk traces and compiles
                piece = solve_chunk(setup, place_on_mesh(members, mesh, _BATCH),
                                     place_on_mesh(shared, mesh, PartitionSpec()))
            if in_host:
                piece = _to_host(piece)
            if throw:
                _raise_for_failed(piece, k * chunk, size, batched, shared, dynamics, options,
                                  permutation)
            bar.update(1)
            if count == 1:
                solution = piece
                break
            if solution is None:  # the whole result in host memory, filled chunk by chunk
                solution = jax.tree_util.tree_map(
                    lambda x: np.empty((size,) + x.shape[1:], x.dtype), piece)
            stop = min(size, (k + 1) * chunk)
            for out, x in zip(jax.tree_util.tree_leaves(solution),
                              jax.tree_util.tree_leaves(piece)):
                out[k * chunk:stop] = x[:stop - k * chunk]
            del piece
    finally:
        bar.close()
    return jax.tree_util.tree_map(lambda x: x[:size], solution)


def _batch_size(batched):
    """B, the common leading axis of the batched inputs (an error naming them if they differ)."""
    sizes = {}
    for path, leaf in jax.tree_util.tree_flatten_with_path(batched)[0]:
        name = ("q0", "u0", "p")[path[0].idx] + jax.tree_util.keystr(path[1:])
        shape = np.shape(leaf)
        if not shape:
            raise ValueError(f"{name} is batched but is a scalar: a batched leaf needs a "
                             "leading batch axis.")
        sizes[name] = shape[0]
    if not sizes:
        raise ValueError("Nothing is batched: pass q0 of shape (B, n) and/or u0 of shape "
                         "(B, m), or parameters with a leading batch axis and "
                         "batched_params=True (or a prefix of p saying which leaves).")
    if len(set(sizes.values())) > 1:
        listed = ", ".join(f"{name} has {b}" for name, b in sizes.items())
        raise ValueError(f"The batch's leading axes disagree: {listed} members.")
    size = next(iter(sizes.values()))
    if size == 0:
        raise ValueError("The batch is empty (leading axis of size 0).")
    return size


def _chunk_size(size, width, chunk_size, max_bytes, dynamics, batched, shared, options):
    """Members per chunk: a multiple of `LANES` members per device, within the bound."""
    if chunk_size is not None and max_bytes is not None:
        raise ValueError("Pass chunk_size or max_bytes, not both.")
    # whole vectors once every device has that many members; a smaller batch is not padded
    # to them (that would multiply its work by up to LANES)
    unit = width * LANES if size >= width * LANES else width
    if max_bytes is not None:
        member = jax.tree_util.tree_map(lambda x: jax.ShapeDtypeStruct(np.shape(x)[1:],
                                                                       jnp.result_type(x)),
                                        batched)
        results = eqx.filter_eval_shape(_member, dynamics, member, shared,
                                        tuple(sorted(options.items())))
        per_member = sum(x.size * x.dtype.itemsize for x in jax.tree_util.tree_leaves(
            (results, member)))
        if max_bytes < per_member * unit:
            raise ValueError(f"max_bytes = {max_bytes} holds less than {unit // width} "
                             f"member(s) per device: a member's results take {per_member} "
                             f"bytes, and there are {width} devices.")
        chunk_size = max_bytes // per_member
    if chunk_size is not None and chunk_size < 1:
        raise ValueError(f"chunk_size must be a positive integer, got {chunk_size}.")
    if chunk_size is None or chunk_size >= size:
        return math.ceil(size / unit) * unit
    return max(unit, chunk_size // unit * unit)


def _member(dynamics, member, shared, options):
    """One member's simulation (throw=False: failures are its own result code)."""
    (q0, u0, p), numbers = eqx.combine(member, shared[0]), shared[1]
    return simulate(dynamics, q0, u0, p, throw=False, **numbers, **dict(options))


def _members(dynamics, members, shared, options):
    """A vmapped solve of the members (with throw=False, `simulate` gives a member whose
    initial state or parameters are not finite its own result code and NaN results)."""
    return jax.vmap(_member, in_axes=(None, 0, None, None))(dynamics, members, shared, options)


def _sharded(setup, members, shared):
    """The members' solve with the batch axis split over the mesh: each device runs its own
    vmapped solve of its share (shard_map), with no communication between devices."""
    dynamics, mesh, options = setup
    arrays, static = eqx.partition(dynamics, eqx.is_array)

    def local(members, shared, arrays):
        return _members(eqx.combine(arrays, static), members, shared, options)

    return jax.shard_map(local, mesh=mesh, in_specs=(_BATCH, PartitionSpec(), PartitionSpec()),
                         out_specs=_BATCH, check_vma=False)(members, shared, arrays)


# The chunks' solve, by XLA's compiler options (`batch_emitters`).
def _laid_out(setup, members, shared):
    """The members' solve as one vmapped program whose batch axis is laid out over the mesh by
    a sharding constraint (XLA partitions it): for hybrid solves (`events`), whose event root
    find equinox closure-converts, comparing the shardings of its arguments, which differ
    inside `shard_map`."""
    dynamics, mesh, options = setup
    members = jax.lax.with_sharding_constraint(members, NamedSharding(mesh, _BATCH))
    return _members(dynamics, members, shared, options)


# (XLA's small-loop hoisting applies, as in a user's own `jax.jit`: on two cores a chunk's
# loop compiled as one function ran as fast or up to 1.8x faster than as the runtime's
# kernels, smooth or hybrid, 256 to 16 384 members; benchmarks/LOG.md, "Identities in the
# written-out code")
_SOLVE_CHUNK = {None: filter_jit(_sharded),
                "fusion": filter_jit(_sharded, compiler_options=FUSION_EMITTERS),
                "events": filter_jit(_laid_out)}


def _emitters(dynamics, batched, shared, mesh, dtype):
    """The key of `_SOLVE_CHUNK` for this system, by its equations' size (as the solve traces
    them, from the first member: the trace is cached and shared with the solve's)."""
    first = jax.tree_util.tree_map(lambda x: jnp.asarray(x[0]), batched)
    q0, u0, p = eqx.combine(first, shared[0])
    q0, u0 = jnp.asarray(q0, dtype), jnp.asarray(u0, dtype)
    t0 = jnp.asarray(shared[1].get("t0", 0.0), dtype)
    size = straight_line_size(dynamics, t0, q0, u0, p)
    options = batch_emitters(size, mesh.devices.flat[0].platform)
    return None if options is None else "fusion"


def _staged(setup, batched, shared, size, chunk, throw):
    """Under a trace: the padded batch as a `lax.map` over chunks of one vmapped solve whose
    batch axis is laid out over the mesh by a sharding constraint (XLA partitions the solve;
    unlike `shard_map`, this composes with every transformation of diffrax's loops)."""
    dynamics, mesh, options = setup
    count = math.ceil(size / chunk)
    padded = _pad(batched, count * chunk)
    chunks = jax.tree_util.tree_map(lambda x: x.reshape((count, chunk) + x.shape[1:]), padded)

    def solve(members):
        members = jax.lax.with_sharding_constraint(members, NamedSharding(mesh, _BATCH))
        return _members(dynamics, members, shared, options)

    solution = jax.lax.map(solve, chunks)
    solution = jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[2:])[:size], solution)
    if throw:
        failed = solution.result != RESULTS.successful
        index = jnp.argmax(failed)
        code = jax.tree_util.tree_map(lambda v: v[index], solution.result)
        q0, u0, _ = eqx.combine(jax.tree_util.tree_map(lambda x: jnp.asarray(x)[index],
                                                       batched), shared[0])
        checks = [(code == item, f"A member of the batch failed: {RESULTS[item]}")
                  for item in _FAILURES]
        # Tied to every output, so that the check stays whatever the caller keeps.
        arrays, static = eqx.partition(solution, eqx.is_array)
        arrays = error_if(arrays, checks, {"member": index, "q0": q0, "u0": u0})
        solution = eqx.combine(arrays, static)
    return solution


def _pad(batched, total):
    """The batch padded to `total` members with copies of its last member."""
    def pad(x):
        extra = total - x.shape[0]
        if extra == 0:
            return x
        tail = jnp if isinstance(x, jax.core.Tracer) else np
        return tail.concatenate([x, tail.repeat(x[-1:], extra, axis=0)])

    return jax.tree_util.tree_map(pad, batched)


def place_on_mesh(tree, mesh, spec):
    """Host (or device) values as global arrays laid out on the mesh (each process supplies
    the parts its devices hold, from the same full value)."""
    sharding = NamedSharding(mesh, spec)

    def place(x):
        x = np.asarray(x)
        return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])

    return jax.tree_util.tree_map(place, tree)


def _to_host(solution):
    """The solution's arrays as NumPy arrays holding the whole batch, in every process."""
    if jax.process_count() > 1:
        return multihost_utils.process_allgather(solution, tiled=True)
    return jax.device_get(solution)


def _raise_for_failed(solution, offset, size, batched, shared, dynamics, options,
                      permutation=None):
    failed = np.flatnonzero(np.asarray(solution.result != RESULTS.successful)[:size - offset])
    if failed.size == 0:
        return
    position = offset + int(failed[0])  # in the order run
    member = jax.tree_util.tree_map(lambda x: np.asarray(x)[position], batched)
    index = position if permutation is None else int(permutation[position])  # as given
    (q0, u0, p), numbers = eqx.combine(member, shared[0]), shared[1]
    try:  # the member alone, for jaxdyn's message naming where it failed
        simulate(dynamics, q0, u0, p, throw=True, **numbers, **dict(options))
        message = RESULTS[jax.tree_util.tree_map(lambda v: v[failed[0]], solution.result)]
    except (RuntimeError, ValueError) as error:
        message = str(error)
    inputs = f"q0 = {np.asarray(q0).tolist()}, u0 = {np.asarray(u0).tolist()}"
    for path, leaf in jax.tree_util.tree_flatten_with_path(member[2])[0]:
        inputs += f", p{jax.tree_util.keystr(path)} = {np.asarray(leaf).tolist()}"
    others = f" ({failed.size} members of its chunk failed)" if failed.size > 1 else ""
    raise RuntimeError(f"Member {index} of the batch of {size} failed{others}. Its initial "
                       f"state: {inputs}.\n\n{message}")


