"""mjstamp: differentiable task and motion planning (STAMP) on MuJoCo MJX.

The public face: what a user writes is importable from here.

    import mjstamp
    from mjstamp import Scene, SolveConfig, Task, costs, load, solve

    mjstamp.configure()                      # float64, compilation cache
    task = Task("mine", Scene("table.xml"), horizon=200)
    ...                                      # variables, symbols, costs, success
    result = solve(task, SolveConfig(particles=64))
    result.save("results/mine")              # plans.json, .npz, scene.mjb, figures
    saved = load("results/mine")

Everything else stays importable from its module (`mjstamp.svgd`,
`mjstamp.verify`, `mjstamp.registry`, ...); `docs/architecture.md` draws
which module may import which.

References:
  Lee et al., "Differentiable Task and Motion Planning via Stein Variational
  Gradient Descent" (STAMP).

N.B. importing mjstamp has no side effects: no XLA flags, no x64, no cache
directory, and JAX is not imported until a name that needs it is used
(`Scene`, `Task`, `costs`, `solve`). `configure()` (which the CLI calls) or
your script sets the rest.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

from mjstamp.version import __version__  # noqa: F401 - the package face hands it on

DEFAULT_CACHE = Path.home() / ".cache" / "mjstamp" / "jax"
FUSION_FLAG = "--xla_cpu_use_fusion_emitters"


def configure(*, precision: str = "float64", compilation_cache: bool = True,
              devices: int | str | None = None, strict_devices: bool = True,
              coordinator: str | None = None, num_processes: int = 1, process_id: int = 0,
              coordinator_timeout_s: float = 60.0, cpu_fusion_emitters: bool = False) -> None:
    """Process-wide JAX settings: precision and the persistent compilation cache.

    N.B. float64 is the default precision: float32 reverse-mode gradients
    through MJX's constraint solver go NaN on contact (see
    `mjstamp.scenes.gradsafe`), and float32 is no faster on a CPU. The
    persistent compilation cache lets the next process load an MJX rollout's
    compiled code instead of compiling it again ($JAX_COMPILATION_CACHE_DIR,
    else ~/.cache/mjstamp/jax).

    Args:
      precision: "float64" or "float32".
      compilation_cache: turn on JAX's persistent compilation cache.
      devices: on a CPU, ask XLA for this many host devices (one per core is
        what `solve`'s `devices` setting shards particles over); must come
        before JAX starts (the first array). "auto": one per core, at most 8,
        shared by the processes of a loopback coordinator, as `mjstamp solve`
        does (`mjstamp.parallel.host_device_count`), and never strict. None
        leaves XLA's default (1).
      strict_devices: when JAX already runs with fewer devices, raise (True)
        or keep them (False).
      coordinator: "host:port" of process 0, to run one solve over several
        processes (machines, or processes of one machine): each process calls
        `configure` with the same coordinator and num_processes and its own
        process_id, then runs the same script; their devices form one set
        that `solve` shards the particles over, and process 0 writes the
        results (`mjstamp.parallel.join_processes`). None: this process alone.
      num_processes: processes in the run (with `coordinator`).
      process_id: this process's index, 0..num_processes-1 (0 hosts the coordinator).
      coordinator_timeout_s: how long to wait for the coordinator.
      cpu_fusion_emitters: XLA's CPU fusion emitters (its default: on). Off
        here unless $XLA_FLAGS says otherwise, and only before JAX starts: on
        a deep body tree they recompute shared work (the kinematics chain) in
        every fused consumer; see benchmarks/results/README.md, "Measurements
        quoted from the code". N.B. the two settings differ in the last bits,
        which can move a chaotic rollout's plans: a seed's plans are those of
        one setting.
    """
    from mjstamp.errors import MjstampError  # noqa: PLC0415

    if precision not in ("float64", "float32"):
        raise MjstampError(f"precision={precision!r} is not valid; valid: float64, float32")
    from jax._src import xla_bridge  # noqa: PLC0415 - asks without starting the backends

    from mjstamp import parallel  # noqa: PLC0415

    if not xla_bridge.backends_are_initialized():
        parallel.set_xla_flag(FUSION_FLAG, cpu_fusion_emitters, keep_users=True)
    if devices is not None:
        if devices == "auto":
            devices = parallel.host_device_count(devices, coordinator=coordinator,
                                                 num_processes=num_processes)
            strict_devices = False  # N.B. "every device there is": whatever JAX already has
        parallel.request_host_devices(devices, strict=strict_devices)
    if coordinator is not None:
        from mjstamp.parallel import join_processes  # noqa: PLC0415

        join_processes(coordinator, num_processes, process_id, timeout_s=coordinator_timeout_s)
    elif (num_processes, process_id) != (1, 0):
        raise MjstampError(f"num_processes={num_processes!r}, process_id={process_id!r} need "
                           "a coordinator (host:port of process 0)")
    import jax  # noqa: PLC0415 - importing mjstamp must not import JAX's backends

    jax.config.update("jax_enable_x64", precision == "float64")
    if compilation_cache:
        cache = os.environ.get("JAX_COMPILATION_CACHE_DIR") or str(DEFAULT_CACHE)
        jax.config.update("jax_compilation_cache_dir", cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


def load(path: str | os.PathLike, *, task: str | None = None):
    """Opens a results directory written by `SolveResult.save` or `mjstamp solve --out`.

    Returns:
      `mjstamp.results.Results`: summary (plans.json), model (scene.mjb),
      trajectories (trajectories.npz).

    Raises:
      MjstampError: not a results directory, an unfinished solve (a
        checkpoint.npz but no plans.json), another schema, another task, or a
        damaged file (truncated, not JSON or .npz, missing arrays or keys,
        wrong shapes); always one line naming the file and what to do.
    """
    from mjstamp.results import load_results  # noqa: PLC0415

    return load_results(path, task=task)


# The names a user writes, imported when first used (PEP 562): `import mjstamp`
# stays cheap and free of JAX until then.
_FACE = {
    "Scene": "mjstamp.scenes",
    "SolveConfig": "mjstamp.config",
    "Task": "mjstamp.tasks",
    "costs": "mjstamp.tasks",
    "solve": "mjstamp.solver",
}


def __getattr__(name: str):
    if name in _FACE:
        import importlib  # noqa: PLC0415

        value = getattr(importlib.import_module(_FACE[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'mjstamp' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_FACE))


if TYPE_CHECKING:
    from mjstamp.config import SolveConfig
    from mjstamp.scenes import Scene
    from mjstamp.solver import solve
    from mjstamp.tasks import Task, costs

__all__ = ["DEFAULT_CACHE", "Scene", "SolveConfig", "Task", "configure", "costs", "load", "solve"]
