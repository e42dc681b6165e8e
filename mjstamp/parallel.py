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

__all__ = ["AXIS", "barrier", "check_devices", "host_device_count", "is_lead", "join_processes",
           "local_device", "particle_mesh", "replicate_outputs", "request_host_devices",
           "shard_count", "shard_particles"]

AXIS = "particles"
_FLAG = "--xla_force_host_platform_device_count"


_LOOPBACK = ("127.0.0.1", "localhost", "[::1]", "::1")


def host_device_count(requested: int | str | None, *, coordinator: str | None = None,
                      num_processes: int = 1) -> int | None:
    """How many CPU host devices to ask XLA for: N, or for "auto" one per core (at most 8).

    The count before JAX starts (`request_host_devices`); `shard_count` is the
    one a solve shards over once it has.

    Args:
      requested: N >= 1, "auto", or None (None: XLA's default, nothing asked).
      coordinator: "host:port" of process 0 in a run over several processes.
        N.B. processes on one machine (a loopback coordinator) share its cores:
        "auto" gives each its share.
      num_processes: processes in that run.

    Raises:
      MjstampError: N is more than this machine's cores (XLA makes as many
        host devices as asked; more than cores only slows).
    """
    if requested is None:
        return None
    cores = os.cpu_count() or 1
    if requested == "auto":
        share = 1
        if coordinator is not None and str(coordinator).rpartition(":")[0] in _LOOPBACK:
            share = num_processes if isinstance(num_processes, int) else 1
        return max(1, min(cores, 8) // max(1, share))
    if requested > cores:
        raise MjstampError(f"--devices {requested}: this machine has {cores} CPU cores "
                           f"(host devices: at most {cores})")
    return requested


def shard_count(requested: int | str | None) -> int:
    """How many devices a solve shards its particles over: N, or every device JAX sees.

    Args:
      requested: N >= 1, or None / "auto": every device (over several
        processes, all of theirs).

    Raises:
      MjstampError: N is not an integer >= 1, or more than JAX sees (`check_devices`).
    """
    k = jax.device_count() if requested is None or requested == "auto" else requested
    check_devices(k)
    return k


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
    set_xla_flag(_FLAG, n)


def set_xla_flag(flag: str, value, *, keep_users: bool = False) -> bool:
    """Puts `flag=value` into $XLA_FLAGS, read once when JAX's backends start.

    Args:
      flag: e.g. "--xla_force_host_platform_device_count".
      value: its value (bools as true/false).
      keep_users: leave a value the user's $XLA_FLAGS already gives.

    Returns:
      whether $XLA_FLAGS now holds this value (False: the user's was kept).
    """
    flags = os.environ.get("XLA_FLAGS", "").split()
    if keep_users and any(f == flag or f.startswith(f"{flag}=") for f in flags):
        return False
    text = str(value).lower() if isinstance(value, bool) else str(value)
    kept = [f for f in flags if not (f == flag or f.startswith(f"{flag}="))]
    os.environ["XLA_FLAGS"] = " ".join([*kept, f"{flag}={text}"])
    return True


def join_processes(coordinator: str, num_processes: int, process_id: int, *,
                   timeout_s: float = 60.0) -> None:
    """Makes this process one of `num_processes` whose devices form one set (jax.distributed).

    Every process runs the same solve: each rolls out the particles on its own
    devices, the kernel sees all of them, and every process ends with the same
    plans. Process 0 hosts the coordinator; only it prints and writes results
    (`is_lead`). On CPUs the processes exchange arrays over Gloo (TCP).

    Args:
      coordinator: "host:port" of process 0 (process 0 listens there).
      num_processes: processes in the run, >= 1.
      process_id: this process's index in [0, num_processes).
      timeout_s: how long a process waits for the coordinator (and process 0
        for the others) before giving up.

    Raises:
      MjstampError: a malformed address or index, JAX already started, process
        0 cannot listen on the port, or another process cannot reach it
        within `timeout_s`: one line each (N.B. checked here because a failed
        `jax.distributed.initialize` aborts the whole process).
    """
    host, port = _address(coordinator)
    if isinstance(num_processes, bool) or not isinstance(num_processes, int) or num_processes < 1:
        raise MjstampError(f"num_processes={num_processes!r} must be an integer >= 1")
    if (isinstance(process_id, bool) or not isinstance(process_id, int)
            or not 0 <= process_id < num_processes):
        raise MjstampError(f"process_id={process_id!r} must be an integer in "
                           f"[0, {num_processes})")
    if not timeout_s > 0:
        raise MjstampError(f"timeout_s={timeout_s!r} must be > 0")
    from jax._src import xla_bridge  # noqa: PLC0415

    if xla_bridge.backends_are_initialized():
        raise MjstampError("join_processes must come before JAX starts (first thing in a "
                           "script: mjstamp.configure(coordinator=..., ...))")
    if process_id == 0:
        _check_listen(host, port)
    else:
        _wait_reachable(host, port, timeout_s)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(str(coordinator), num_processes=num_processes,
                               process_id=process_id,
                               initialization_timeout=max(1, int(timeout_s)))


def _address(coordinator) -> tuple[str, int]:
    """("host", port) from "host:port", or a one-line MjstampError."""
    text = str(coordinator)
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise MjstampError(f"coordinator={text!r} must be HOST:PORT with a port in 1..65535 "
                           "(e.g. 127.0.0.1:4321)")
    return host.strip("[]"), int(port)


def _check_listen(host: str, port: int) -> None:
    import socket  # noqa: PLC0415

    try:
        with socket.create_server(("", port), reuse_port=False):
            pass
    except OSError as e:
        raise MjstampError(f"coordinator {host}:{port}: process 0 cannot listen on port "
                           f"{port} ({e.strerror or 'refused'}); pick a free port") from None


def _wait_reachable(host: str, port: int, timeout_s: float) -> None:
    import socket  # noqa: PLC0415
    import time  # noqa: PLC0415

    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection((host, port), timeout=min(5.0, timeout_s)):
                return
        except OSError as e:
            if time.monotonic() >= deadline:
                raise MjstampError(f"coordinator {host}:{port} not reachable within "
                                   f"{timeout_s:g} s ({e.strerror or e}); start process 0 "
                                   "first, with the same --coordinator") from None
            time.sleep(0.2)


def local_device():
    """This process's first device: where unsharded work (one scene's model, a batch) lives.

    N.B. not `jax.devices()[0]` (MJX's default), which in a run over several
    processes is process 0's device, out of reach of the others.
    """
    return jax.local_devices()[0]


def barrier(name: str) -> None:
    """Waits until every process of a run over several reaches `name` (alone: returns)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils  # noqa: PLC0415

        multihost_utils.sync_global_devices(name)


def is_lead() -> bool:
    """Whether this process prints and writes results: always, unless it is not process 0."""
    return jax.process_index() == 0


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


def replicate_outputs(fn: Callable, k: int) -> Callable:
    """`fn` whose outputs are whole on each of the first k devices (k > 1).

    N.B. the STAMP step's outputs (particles, optimizer state, diagnostics):
    every process of a run over several (`join_processes`) can then read them
    without a collective, so the loop and its checkpoints stay per-process; and
    within one process, another function compiled for the k devices takes them
    as they are, without a round trip through the host to reshard them (an
    evaluation handed to its update, `mjstamp.svgd.steps`).
    """
    if k == 1:
        return fn
    place = replicated(particle_mesh(k))
    return lambda *args: jax.lax.with_sharding_constraint(fn(*args), place)


def shard_particles(fn: Callable, k: int) -> Callable:
    """`fn` over (n, d) particles, evaluated k-ways sharded along the particles.

    Args:
      fn: a batched function of (n, d) particles (and of further arguments,
        which every device gets whole) whose outputs are arrays (or pytrees of
        arrays) with the particles first, (n, ...).
      k: devices; 1 returns `fn` itself.

    Returns:
      A function with `fn`'s signature and outputs (whole (n, ...) arrays),
      differentiable like `fn` (`jax.vjp`, `jax.jvp` go through `shard_map`).
    """
    if k == 1:
        return fn
    mesh = particle_mesh(k)
    cache: dict[int, Callable] = {}

    def sharded(x, *rest):
        """`fn(x, *rest)`: x split along the particles, `rest` (pytrees) whole on each device."""
        if len(rest) not in cache:
            # N.B. check_vma=False: MJX's lax.cond branches mix per-device and replicated
            # values, which the varying-axes check rejects though each device is independent.
            cache[len(rest)] = jax.shard_map(fn, mesh=mesh, in_specs=(P(AXIS), *[P()] * len(rest)),
                                             out_specs=P(AXIS), check_vma=False)
        n = x.shape[0]
        pad = -n % k
        if pad:  # copies of the last particle; their results are dropped below
            x = jnp.concatenate([x, jnp.broadcast_to(x[-1:], (pad, *x.shape[1:]))])
        out = cache[len(rest)](x, *rest)
        return jax.tree.map(lambda a: a[:n], out) if pad else out

    return sharded
