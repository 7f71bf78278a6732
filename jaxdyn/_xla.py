"""The switches of XLA's CPU compiler that jaxdyn sets at import.

Three, each for programs that jaxdyn forms (benchmarks/LOG.md, "XLA's CPU code generators"
and "Loops as one function"):

- the fusion emitters compile the straight-line scalar programs of small systems
  (`jaxdyn._unroll`) into code that runs 50–2500× slower than XLA's elemental emitters: a UR5
  arm's forward dynamics costs 1 ms per state in a vmapped batch with them, 0.4 µs without;
- YNNPACK fusions take over the small batched products of 6 × 6 and 3 × 3 blocks in a tree's
  recursions and run them several times slower than XLA's own loops: a humanoid's forward
  dynamics (G1) costs 49 µs per state in a batch with them, 15 µs without;
- small loops become one function. XLA's CPU runtime runs a loop as a sequence of kernels
  per iteration, each launched by the runtime at a cost of tens of nanoseconds, and compiles a
  loop into a single function only when one iteration of its body touches under a kilobyte.
  A robot's recursions over its links are hundreds of small kernels per state, and a step of
  a small system's integration tens: with the bound at `SMALL_LOOP_BYTES` such loops run as
  one compiled function (per state in a batch of 1024, the G1 humanoid's forward dynamics
  12.0 → 8.7 µs, its mass matrix 8.1 → 5.8; a double pendulum's `simulate` over 100 s
  6.4 → 2.8 ms, a chain of 10 rods' 200 → 39 ms). A loop so compiled runs on one core, where
  the runtime spreads the large kernels of a batch over the cores; measured on two cores, a
  vmapped solve of small systems still runs as fast or faster as one function (1024 double
  pendulums, T as 2-vectors: 485 against 663 ms), except near a few hundred members (256:
  147 against 127 ms), and so does `simulate_batch` (which compiled its solves without it
  until measured again; benchmarks/LOG.md, "Loops as one function" and "Identities in the
  written-out code").

The switches are read when JAX first starts its CPU backend, so they are set here, before
jaxdyn creates any array, unless the user chose values of their own. Where JAX started first,
the programs jaxdyn compiles itself still carry the YNNPACK switch (a program's own option);
the small-loop threshold cannot be given per program, and jaxdyn warns, with what it costs
(benchmarks/LOG.md, "The order of the imports").
"""

import os
import warnings

import jax._src.xla_bridge as xla_bridge


# The bytes that one iteration of a loop's body may touch for XLA to compile the loop as one
# function: one state of a humanoid's recursions (Talos, 45 bodies) or of a chain of 100 links
# fits, a step of the vmapped solve of a thousand small systems does not.
SMALL_LOOP_BYTES = 1_000_000

SWITCHES = {"xla_cpu_use_fusion_emitters": "false",
            "xla_cpu_experimental_ynn_fusion_type": "",
            "xla_backend_extra_options":
                f"xla_cpu_small_while_loop_byte_threshold={SMALL_LOOP_BYTES}"}

# A switch that a single program can also carry (`jax.jit(compiler_options=...)`): every
# program jaxdyn compiles itself does, so that its speed depends less on the order of the
# imports. The small-loop threshold, a value of XLA's `xla_backend_extra_options` map, cannot
# be given per program (XLA refuses a map in a program's options), only at the process's
# start; and the fusion emitters are worth turning off only together with it (without it, a
# double pendulum's `simulate` over 100 s ran 5.9 ms with them and 8.0-8.4 without).
PER_PROGRAM = {"xla_cpu_experimental_ynn_fusion_type": ""}

_unset = [name for name in SWITCHES if name not in os.environ.get("XLA_FLAGS", "")]
_started = xla_bridge.backends_are_initialized() and xla_bridge.default_backend() == "cpu"
if _unset:
    os.environ["XLA_FLAGS"] = " ".join(
        [os.environ.get("XLA_FLAGS", "")] + [f"--{name}={SWITCHES[name]}"
                                             for name in _unset]).strip()
    if _started and "xla_backend_extra_options" in _unset:
        warnings.warn(
            "JAX started its backends before jaxdyn was imported, so XLA will not compile "
            "small loops as one function in this process: jaxdyn's own calls on the CPU run "
            "robots' recursions and small systems' solves up to 1.6x slower (G1's forward "
            "dynamics over a batch of 1024 1.6x, a double pendulum's simulate over 100 s "
            "1.35x), and programs you compile yourself with jax.jit up to 2.5x slower (1.7x "
            "with jax.jit(..., compiler_options=jaxdyn.compiler_options())). Import jaxdyn "
            "before the first JAX computation, or start Python with XLA_FLAGS=\""
            + " ".join(f"--{name}={value}" for name, value in SWITCHES.items()) + "\".",
            stacklevel=2)


def compiler_options() -> dict:
    """XLA's options for a program you compile yourself around jaxdyn's calls, as
    `jax.jit(f, compiler_options=jaxdyn.compiler_options())`: the switch of XLA's CPU
    compiler that jaxdyn's own programs carry, YNNPACK fusions off (they run the small
    batched products of robots' recursions several times slower), unless you set it yourself
    in `XLA_FLAGS`. Needed only where JAX started before `import jaxdyn` (jaxdyn then warns);
    otherwise the process already has it. An empty dict off the CPU."""
    if xla_bridge.default_backend() != "cpu":
        return {}
    return {name: value for name, value in PER_PROGRAM.items() if name in _unset}


# Whether XLA compiles a loop of small iterations as one function in this process (jaxdyn's
# switch, in effect): array programs then batch a state at a time (`jaxdyn._chunking`).
SMALL_LOOPS_ONE_FUNCTION = "xla_backend_extra_options" in _unset and not _started
