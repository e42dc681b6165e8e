"""Particles sharded over devices: each device rolls out its share, the kernel sees them all.

A solve's cost is its rollouts: n particles, each its own MJX rollout, no
interaction until the n x n kernel. `shard_particles(fn, k)` runs a batched
function of particles (the log posterior, its target at the hard decode) under
`jax.shard_map` over a one-axis `Mesh` of k devices: each device rolls out
n / k particles; the results come back as whole (n, ...) arrays, so the kernel
and the optimizer (outside, under `jax.jit`) read every particle, and XLA
gathers the per-device pieces for them. A particle count that does not divide
by k is padded with copies of the last particle, whose results are dropped.

On a CPU, devices are host devices: `mjstamp.configure(devices=N)` (or the
CLI's `--devices N`) asks XLA for N before JAX starts, one per core. On GPUs,
the devices are the local GPUs. Across machines, `jax.distributed.initialize()`
before `configure` makes every process's devices one set (see the README).

Each particle's rollout is the same computation on whichever device it runs,
but XLA compiles a smaller batch with other vectorised reductions: scores can
differ in the last bits (0 for billiards' forward-mode scores, 7e-12 for its
reverse-mode ones between 1 and 2 devices), and a task that amplifies rounding
can end with slightly different plans (billiards, seed 0: 69 verified plans in
17 task plans on 1 CPU device, 68 in 16 on 2). The tiny test task gives
the same plans on 1 and 2 devices, costs and motion plans within 1e-12
(`tests/test_parallel.py`).
"""

from __future__ import annotations

import os
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from mjstamp.errors import MjstampError

__all__ = ["AXIS", "check_devices", "particle_mesh", "request_host_devices", "shard_particles"]

AXIS = "particles"
_FLAG = "--xla_force_host_platform_device_count"


def request_host_devices(n: int, *, strict: bool = True) -> None:
    """Asks XLA for n CPU host devices; only possible before JAX's backends start.

    Args:
      n: host devices wanted.
      strict: when JAX already runs with fewer devices, raise (True) or keep
        what it has (False: the CLI's `--devices auto` called from a running
        Python session, a test or a notebook).

    Raises:
      MjstampError: n is not a positive integer, or JAX already runs with
        fewer devices and `strict` (the flag is read once, at JAX's start).
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise MjstampError(f"devices={n!r} must be an integer >= 1")
    from jax._src import xla_bridge  # noqa: PLC0415 - the only way to ask without starting it

    if xla_bridge.backends_are_initialized():
        if strict and jax.device_count() < n:
            raise MjstampError(
                f"devices={n}: JAX already runs with {jax.device_count()} "
                f"{jax.default_backend()} device(s); ask for host devices before JAX starts "
                "(mjstamp.configure(devices=N) first thing in a script, or --devices N)"
            )
        return
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split() if not f.startswith(_FLAG)]
    os.environ["XLA_FLAGS"] = " ".join([*flags, f"{_FLAG}={n}"])


def check_devices(k: int) -> list:
    """The first k devices, or a one-line MjstampError naming how many there are."""
    if isinstance(k, bool) or not isinstance(k, int) or k < 1:
        raise MjstampError(f"devices={k!r} must be an integer >= 1")
    devices = jax.devices()
    if k > len(devices):
        hint = (" (ask for host devices before JAX starts: mjstamp.configure(devices=N), or "
                "--devices N on the command line)" if jax.default_backend() == "cpu" else "")
        raise MjstampError(f"devices={k} but JAX sees {len(devices)} {jax.default_backend()} "
                           f"device(s){hint}")
    return devices[:k]


def particle_mesh(k: int) -> Mesh:
    """A one-axis mesh ("particles") over the first k devices."""
    return Mesh(np.array(check_devices(k)), (AXIS,))


def replicated(mesh: Mesh) -> NamedSharding:
    """The sharding that holds a whole array on every device of `mesh`."""
    return NamedSharding(mesh, P())


def shard_particles(fn: Callable, k: int) -> Callable:
    """`fn` over (n, d) particles, evaluated k-ways sharded along the particles.

    Args:
      fn: a batched function of (n, d) particles whose outputs are arrays (or
        pytrees of arrays) with the particles first, (n, ...).
      k: devices; 1 returns `fn` itself.

    Returns:
      A function with `fn`'s signature and outputs (whole (n, ...) arrays),
      differentiable like `fn` (`jax.vjp`, `jax.jvp` go through `shard_map`).
    """
    if k == 1:
        return fn
    mesh = particle_mesh(k)
    # N.B. check_vma=False: MJX's lax.cond branches mix per-device and replicated
    # values, which the varying-axes check rejects though each device is independent.
    inner = jax.shard_map(fn, mesh=mesh, in_specs=P(AXIS), out_specs=P(AXIS), check_vma=False)

    def sharded(x):
        n = x.shape[0]
        pad = -n % k
        if pad:  # copies of the last particle; their results are dropped below
            x = jnp.concatenate([x, jnp.broadcast_to(x[-1:], (pad, *x.shape[1:]))])
        out = inner(x)
        return jax.tree.map(lambda a: a[:n], out) if pad else out

    return sharded
