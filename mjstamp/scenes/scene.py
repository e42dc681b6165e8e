"""Scene: an MJCF model, its gradient-safe MJX twin and its names, resolved once."""

from __future__ import annotations

import copy
import dataclasses
import functools
import importlib.resources
import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from mjstamp import colliders
from mjstamp._mjx import mjx
from mjstamp.errors import MjstampError, valid_list
from mjstamp.parallel import local_device
from mjstamp.scenes import gradsafe
from mjstamp.scenes.collisions import check_collidable
from mjstamp.scenes.rollout import build_rollout, cast_floats

_SOLVERS = {"newton": mujoco.mjtSolver.mjSOL_NEWTON, "cg": mujoco.mjtSolver.mjSOL_CG}
_CUSTOM_PREFIX = "mjstamp.grad."


@dataclasses.dataclass(frozen=True)
class GradOptions:
    """Solver options of the model used for differentiable (MJX) rollouts.

    The scene's own options (its MJCF `<option>`) stay untouched in `Scene.m` and
    are what plans are verified with; these replace them in `Scene.m_grad` and
    `Scene.mx` only. Precedence, lowest first: these defaults, then
    `<custom><numeric name="mjstamp.grad.FIELD" data="VALUE"/></custom>` in the
    MJCF, then the fields a caller passes.

    Attributes:
      solver: "newton" or "cg". Newton, because with a single iteration it
        already lands at (or very near) the solution of a small contact problem,
        where CG's first step is only a steepest-descent step.
      iterations: solver iterations k >= 1. N.B. MJX runs more than one in a
        `lax.while_loop`, which reverse-mode AD cannot go through; every Scene
        applies `gradsafe.patch_mjx()`, which runs the same loop as a
        fixed-trip `scan` (no-ops once converged), so gradients exist for any
        k and the forward values are MJX's own. One iteration is exact only for
        soft, frictionless contact problems; `mjstamp.scenes.fidelity`
        measures how many a scene needs to match its own solver, and `solve`
        calibrates it per task. Cost grows about linearly with k: under `vmap`
        every particle runs all k trips.
      ls_iterations: line-search iterations (a `scan`, so AD goes through). A
        few suffice for a Newton step on these small problems; each costs a
        full evaluation of the constraint cost.
      timestep: integration step in seconds; None keeps the MJCF's. Contact
        softness (geom `solref`/`solimp`) always comes from the MJCF: MJX does
        not support MuJoCo's global contact override.
      warmstart: keep the solver's warm start. Off: one Newton iteration from
        the smooth acceleration is the same every step, whatever the history.
      gradient: how the solver is differentiated (`gradsafe.gradient_mode`):
        "unrolled" differentiates each of the `iterations`; "implicit" runs
        MJX's own solver loop (up to `iterations`, stopping at the MJCF's
        tolerance) forward only and differentiates one Newton step from its
        solution, the implicit-function derivative. Implicit is exact where
        the solver converges, for about the cost of one unrolled iteration;
        one unrolled iteration is cheapest where it is already exact (soft
        frictionless contacts). `solve` picks between them per task.
    """

    solver: str = "newton"
    iterations: int = 1
    ls_iterations: int = 4
    timestep: float | None = None
    warmstart: bool = False
    gradient: str = "unrolled"

    def __post_init__(self):
        if self.solver not in _SOLVERS:
            raise MjstampError(
                f"GradOptions.solver={self.solver!r} is not supported; valid: "
                f"{valid_list(_SOLVERS)}"
            )
        if self.gradient not in gradsafe.GRADIENTS:
            raise MjstampError(
                f"GradOptions.gradient={self.gradient!r} is not valid; valid: "
                f"{valid_list(gradsafe.GRADIENTS)}"
            )
        if self.gradient == "implicit" and self.solver != "newton":
            raise MjstampError(
                "GradOptions.gradient='implicit' needs solver='newton' (its Hessian gives "
                "the implicit derivative)"
            )
        if int(self.iterations) < 1:
            raise MjstampError(
                f"GradOptions.iterations={self.iterations} must be >= 1"
            )
        if int(self.ls_iterations) < 1:
            raise MjstampError(
                f"GradOptions.ls_iterations={self.ls_iterations} must be >= 1"
            )
        if self.timestep is not None and not self.timestep > 0:
            raise MjstampError(f"GradOptions.timestep={self.timestep} must be > 0")

    def apply(self, m: mujoco.MjModel) -> mujoco.MjModel:
        """Returns a copy of `m` with these options, and without what MJX ignores."""
        m = copy.copy(m)
        m.opt.solver = _SOLVERS[self.solver]
        m.opt.iterations = self.iterations
        m.opt.ls_iterations = int(self.ls_iterations)
        if self.timestep is not None:
            m.opt.timestep = self.timestep
        if self.warmstart:
            m.opt.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_WARMSTART)
        else:
            m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_WARMSTART)
        # N.B. MJX 3.17 runs no noslip solver and never puts bodies to sleep, yet
        # accepts both options: the C twin drops them, or it would follow the
        # scene's physics where MJX does not (fuzzed: 0.07 m against MJX's 0.99 m).
        m.opt.noslip_iterations = 0
        m.opt.enableflags &= ~int(mujoco.mjtEnableBit.mjENBL_SLEEP)
        return m


def _options_from_custom(m: mujoco.MjModel) -> dict[str, Any]:
    """Reads `mjstamp.grad.*` overrides from the MJCF's <custom> numerics."""
    fields = {f.name: f.type for f in dataclasses.fields(GradOptions)}
    out = {}
    for i in range(m.nnumeric):
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_NUMERIC, i)
        if not name or not name.startswith(_CUSTOM_PREFIX):
            continue
        key = name[len(_CUSTOM_PREFIX) :]
        numeric = [k for k in fields if k not in ("solver", "gradient")]
        if key not in numeric:
            raise MjstampError(
                f"unknown custom numeric {name!r}; valid: "
                f"{valid_list(_CUSTOM_PREFIX + k for k in numeric)}"
            )
        adr = m.numeric_adr[i]
        value = float(m.numeric_data[adr])
        out[key] = bool(value) if key == "warmstart" else value
        if key in ("iterations", "ls_iterations"):
            out[key] = int(value)
    return out


_NAME_KINDS = {
    "body": (mujoco.mjtObj.mjOBJ_BODY, "nbody"),
    "geom": (mujoco.mjtObj.mjOBJ_GEOM, "ngeom"),
    "joint": (mujoco.mjtObj.mjOBJ_JOINT, "njnt"),
    "site": (mujoco.mjtObj.mjOBJ_SITE, "nsite"),
    "actuator": (mujoco.mjtObj.mjOBJ_ACTUATOR, "nu"),
}


def _load_model(source, assets: dict[str, bytes] | None) -> tuple[mujoco.MjModel, str]:
    """Compiles `source` into an MjModel; returns it with a label for messages."""
    if hasattr(source, "to_xml_string") and hasattr(source, "get_assets"):
        # A dm_control.mjcf RootElement: composition of scenes goes through mjcf.
        label = f"mjcf model {getattr(source, 'model', None)!r}"
        try:
            xml = source.to_xml_string()
            all_assets = dict(source.get_assets())
        except Exception as e:  # noqa: BLE001 - dm_control raises many types
            raise MjstampError(f"{label}: {_one_line(e)}") from None
        all_assets.update(assets or {})
        return _compile(lambda: mujoco.MjModel.from_xml_string(xml, all_assets), label)
    if isinstance(source, Path) or (
        isinstance(source, str) and not source.lstrip().startswith("<")
    ):
        path = Path(source)
        label = str(path)
        if not path.is_file():
            raise MjstampError(f"{label}: MJCF file not found")
        if assets:
            xml = path.read_text()
            return _compile(
                lambda: mujoco.MjModel.from_xml_string(xml, assets), label
            )
        return _compile(lambda: mujoco.MjModel.from_xml_path(str(path)), label)
    if isinstance(source, str):
        return _compile(
            lambda: mujoco.MjModel.from_xml_string(source, assets or {}),
            "MJCF string",
        )
    raise MjstampError(
        f"cannot build a Scene from {type(source).__name__}; valid: an MJCF path, an "
        "MJCF string or a dm_control.mjcf element"
    )


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return text or type(e).__name__


def _compile(fn, label: str) -> tuple[mujoco.MjModel, str]:
    try:
        return fn(), label
    except ValueError as e:
        # N.B. MuJoCo's XML errors span several lines ("XML Error: ...\nElement ...").
        raise MjstampError(f"{label}: {_one_line(e)}") from None


def package_model_path(filename: str) -> Path:
    """Path of an MJCF file shipped in mjstamp's `models/` (importlib.resources)."""
    ref = importlib.resources.files("mjstamp.models").joinpath(filename)
    return Path(os.fspath(ref))


def shipped_models() -> list[str]:
    """Names of the MJCF files shipped in `models/`, without `.xml`."""
    root = importlib.resources.files("mjstamp.models")
    return sorted(p.name[:-4] for p in root.iterdir() if p.name.endswith(".xml"))


MENAGERIE_PACKAGE = "mujoco-menagerie"  # pip name of the mujoco_menagerie index


def menagerie_model_path(robot: str, entry: str | None = None, *,
                         download: bool = True) -> Path:
    """Path of a MuJoCo Menagerie robot's MJCF file, from the `mujoco_menagerie` package.

    The package is an index: each robot is fetched from the network into its cache
    (`~/.cache/mujoco_menagerie`, `MENAGERIE_CACHE_DIR`) on first use, and read from
    there offline afterwards (`mujoco-menagerie prefetch NAME` fills it ahead).

    Args:
      robot: its name, as `mujoco_menagerie.names()` spells it (e.g. "franka_emika_panda").
      entry: one of the robot's top-level MJCFs (`mujoco_menagerie.get(robot).entry_names`,
        e.g. "scene", "mjx_scene", "panda"); None: its default scene, as
        `mujoco_menagerie.load` picks.
      download: fetch a robot missing from the cache; False: never touch the network.

    Raises:
      MjstampError: one line naming the robot, what is missing and what to run: the
        package not installed, an unknown robot or entry point, a robot not cached
        that could not (or may not) be downloaded.
    """
    label = f"menagerie robot {robot!r}"
    try:
        import mujoco_menagerie as mm  # noqa: PLC0415 - optional: only this loader needs it
    except ImportError as e:
        if e.name not in (None, "mujoco_menagerie"):  # installed, but a dependency is not
            raise MjstampError(f"{label}: mujoco_menagerie does not import ({_one_line(e)})"
                               ) from None
        raise MjstampError(
            f"{label}: the mujoco_menagerie package is not installed; run `pip install "
            f"{MENAGERIE_PACKAGE}` (it downloads each robot on first use, or ahead with "
            f"`mujoco-menagerie prefetch {robot}`)"
        ) from None
    try:
        record = mm.get(robot)
    except LookupError as e:
        names = mm.names()
        near = list(getattr(e, "suggestions", None) or [])
        hint = f"did you mean {near[0]!r}? " if near else ""
        some = valid_list(names) if len(names) <= 6 else (
            f"{', '.join(names[:6])}, ... ({len(names)} in all; `mujoco-menagerie names` "
            "lists them)")
        raise MjstampError(f"unknown menagerie robot {robot!r}; {hint}valid: {some}") from None
    if entry is not None and entry not in record.entry_names:
        raise MjstampError(
            f"{label} has no entry point {entry!r}; valid: {valid_list(record.entry_names)}"
        )
    cache = mm.Cache()
    fetch = f"run `mujoco-menagerie prefetch {robot}` where there is network"
    if not download and not cache.root and not cache.is_cached(record):
        raise MjstampError(
            f"{label} is not in the menagerie cache ({cache.dir}) and download=False; {fetch}, "
            "or set MENAGERIE_CACHE_DIR to a cache that holds it"
        )
    try:
        return Path(record.xml(entry, cache))
    except mm.DownloadError as e:
        raise MjstampError(
            f"{label} is not in the menagerie cache ({cache.dir}) and could not be downloaded "
            f"({_one_line(e)}); {fetch}, or set MENAGERIE_CACHE_DIR to a cache that holds it"
        ) from None
    except mm.MenagerieError as e:
        raise MjstampError(f"{label}: {_one_line(e)}") from None


class Scene:
    """An MJCF scene: MuJoCo model, gradient-safe MJX model, and resolved names.

    Attributes:
      name: a label for messages (the model name or file stem).
      m: the `MjModel` with the scene's own options; plans are verified with it.
      m_grad: a copy with `grad_options` applied; MuJoCo C twin of `mx`.
      mx: the `mjx.Model` of `m_grad`, in `dtype`.
      dtype: float dtype of MJX rollouts (see `precision`).
      grad_options: the `GradOptions` in force.
    """

    def __init__(
        self,
        source,
        *,
        grad_options: GradOptions | None = None,
        precision: str | None = None,
        assets: dict[str, bytes] | None = None,
        name: str | None = None,
        **overrides,
    ):
        """Builds a scene.

        Args:
          source: an MJCF file path, an MJCF XML string, or a `dm_control.mjcf`
            RootElement (its mesh assets included). By name: `Scene.shipped(name)`
            for mjstamp's own scenes, `Scene.menagerie(robot)` for a MuJoCo
            Menagerie robot (the optional `mujoco_menagerie` package and its cache).
          grad_options: gradient-safe solver options (default `GradOptions()`,
            then MJCF `<custom>` overrides). Keyword `overrides` (e.g.
            `ls_iterations=8`) replace single fields on top.
          precision: "float32" or "float64" for MJX rollouts; must agree with
            `jax_enable_x64`, which it follows when None (the default). The
            CLI enables x64: see `mjstamp.scenes.gradsafe` for why.
          assets: extra files (name -> bytes) for meshes and includes.
          name: label for messages; defaults to the model name.
          **overrides: single `GradOptions` fields, e.g. `ls_iterations=8`.

        Raises:
          MjstampError: malformed MJCF, missing file, bad option.
        """
        self.m, self._label = _load_model(source, assets)
        # N.B. before the check and any trace of mjx.collision: MuJoCo C's own
        # colliders, ported, replace MJX's where MJX computes other contacts.
        colliders.patch_collisions()
        check_collidable(self.m, self._label)
        self.name = name or self.m.names[: self.m.names.index(b"\0")].decode() or (
            Path(source).stem if isinstance(source, (str, Path)) else "scene"
        )
        x64 = bool(jax.config.jax_enable_x64)
        if precision is None:
            precision = "float64" if x64 else "float32"
        if precision not in ("float32", "float64"):
            raise MjstampError(
                f"precision={precision!r} is not valid; valid: float32, float64"
            )
        if (precision == "float64") != x64:
            # N.B. MJX allocates with JAX's default float type, so a float32 model
            # in an x64 process is silently promoted back to float64.
            raise MjstampError(
                f"precision={precision!r} needs jax_enable_x64={not x64}; call "
                f"jax.config.update('jax_enable_x64', {not x64}) before building "
                "the Scene, or leave precision unset to follow that flag"
            )
        fields = dataclasses.asdict(grad_options or GradOptions())
        fields.update(_options_from_custom(self.m))
        unknown = set(overrides) - set(fields)
        if unknown:
            raise MjstampError(
                f"unknown option {sorted(unknown)[0]!r}; valid: {valid_list(fields)}"
            )
        fields.update(overrides)
        self.grad_options = GradOptions(**fields)
        self.m_grad = self.grad_options.apply(self.m)
        # N.B. before any trace of mjx.step: MJX's solver forms infinite JVP
        # coefficients on inactive contact rows (NaN gradients with elliptic
        # cones even in float64, with hinges in float32); the patch changes
        # derivatives only, forward values stay bit-identical. See gradsafe.
        gradsafe.patch_mjx()
        self.dtype = jnp.float64 if precision == "float64" else jnp.float32
        self.precision = precision
        self.mx = cast_floats(mjx.put_model(self.m_grad, device=local_device()), self.dtype)
        self._names = {
            kind: {
                mujoco.mj_id2name(self.m, obj, i): i
                for i in range(getattr(self.m, count))
                if mujoco.mj_id2name(self.m, obj, i)
            }
            for kind, (obj, count) in _NAME_KINDS.items()
        }
        self._rollouts: dict[Any, Any] = {}

    @classmethod
    def shipped(cls, name: str, **kwargs) -> Scene:
        """Loads a scene shipped in `models/` by name (e.g. "billiards")."""
        names = shipped_models()
        if name not in names:
            raise MjstampError(f"unknown scene {name!r}; valid: {valid_list(names)}")
        return cls(package_model_path(f"{name}.xml"), name=name, **kwargs)

    @classmethod
    def menagerie(cls, robot: str, entry: str | None = None, *, download: bool = True,
                  **kwargs) -> Scene:
        """Loads a MuJoCo Menagerie robot by name, through the `mujoco_menagerie` package.

            Scene.menagerie("franka_emika_panda", "mjx_scene")

        Where a robot has an MJX entry point (`mjx_scene`: primitive collision geoms,
        solver settings tuned for MJX) it is the one to plan on; the default scene
        collides the visual meshes. See `menagerie_model_path` for `entry`,
        `download` and the errors (one line each: package not installed, unknown
        robot, not cached and no network).

        Args:
          robot: its name (`mujoco_menagerie.names()`); also the scene's `name`
            unless one is given.
          entry: its entry point; None: its default scene.
          download: fetch it when the cache lacks it; False: the cache or an error.
          **kwargs: as `Scene` (`name`, `grad_options`, `precision`, single
            `GradOptions` fields).
        """
        path = menagerie_model_path(robot, entry, download=download)
        kwargs.setdefault("name", robot)
        return cls(path, **kwargs)

    def __repr__(self) -> str:
        m = self.m
        return (
            f"Scene({self.name!r}, nq={m.nq}, nv={m.nv}, nu={m.nu}, "
            f"ngeom={m.ngeom}, precision={self.precision!r})"
        )

    # Names, resolved once at construction.

    def names(self, kind: str) -> list[str]:
        """All names of one kind: body, geom, joint, site or actuator."""
        return list(self._names[kind])

    def id(self, kind: str, name: str | int) -> int:
        """Id of a named object; ints pass through after a range check."""
        table = self._names[kind]
        count = getattr(self.m, _NAME_KINDS[kind][1])
        if isinstance(name, (int, np.integer)) and not isinstance(name, bool):
            if 0 <= int(name) < count:
                return int(name)
        elif isinstance(name, str) and name in table:
            return table[name]
        choices = ([valid_list(table)] if table else []) + (
            [f"an id in 0..{count - 1}"] if count else [])
        raise MjstampError(
            f"unknown {kind} {name!r} in scene {self.name!r} ({self._label}); "
            f"valid: {' or '.join(choices) or '(none)'}"
        )

    def body(self, name: str | int) -> int:
        """Body id."""
        return self.id("body", name)

    def geom(self, name: str | int) -> int:
        """Geom id."""
        return self.id("geom", name)

    def joint(self, name: str | int) -> int:
        """Joint id."""
        return self.id("joint", name)

    def site(self, name: str | int) -> int:
        """Site id."""
        return self.id("site", name)

    def actuator(self, name: str | int) -> int:
        """Actuator id."""
        return self.id("actuator", name)

    def qpos_adr(self, joint: str | int) -> int:
        """Address in qpos of a joint's first coordinate."""
        return int(self.m.jnt_qposadr[self.joint(joint)])

    def dof_adr(self, joint: str | int) -> int:
        """Address in qvel of a joint's first degree of freedom."""
        return int(self.m.jnt_dofadr[self.joint(joint)])

    @functools.cached_property
    def length_scale(self) -> float:
        """The scene's size in metres: the diagonal of what can collide or mark a goal.

        The bounding box, at `qpos0`, of every geom but planes and height fields
        (each geom's own box, `geom_aabb`, turned into the world) and of every
        site. N.B. not
        MuJoCo's `m.stat.extent`, which a large floor plane inflates (a 50 m
        plane under a 2 m table gives 10 m). Defaults that need a length (the
        fidelity tolerance, softmin temperatures) are fractions of it.
        """
        m = self.m
        d = mujoco.MjData(m)
        mujoco.mj_kinematics(m, d)
        unbounded = (int(mujoco.mjtGeom.mjGEOM_PLANE), int(mujoco.mjtGeom.mjGEOM_HFIELD))
        keep = ~np.isin(m.geom_type, unbounded)
        mat = d.geom_xmat[keep].reshape(-1, 3, 3)
        centre = d.geom_xpos[keep] + np.einsum("gij,gj->gi", mat, m.geom_aabb[keep, :3])
        half = np.einsum("gij,gj->gi", np.abs(mat), m.geom_aabb[keep, 3:])
        lo = np.concatenate([centre - half, d.site_xpos])
        hi = np.concatenate([centre + half, d.site_xpos])
        if not len(lo):
            return 1.0  # nothing bounded: a metre, MuJoCo's own default extent
        return float(max(np.linalg.norm(hi.max(axis=0) - lo.min(axis=0)), 1e-6))

    def initial_state(self) -> tuple[np.ndarray, np.ndarray]:
        """The model's initial (qpos0, zero qvel), as float64 numpy arrays."""
        return self.m.qpos0.copy(), np.zeros(self.m.nv)

    def with_grad_options(self, **fields) -> Scene:
        """A scene on the same MJCF model with some `GradOptions` fields replaced.

        The C model `m` (what plans are verified with) and the names are shared;
        only the gradient model (`m_grad`, `mx`) and the compiled rollouts are
        new. Returns `self` when nothing changes.
        """
        unknown = sorted(set(fields) - {f.name for f in dataclasses.fields(GradOptions)})
        if unknown:
            raise MjstampError(
                f"unknown option {unknown[0]!r}; valid: "
                f"{valid_list(f.name for f in dataclasses.fields(GradOptions))}"
            )
        options = dataclasses.replace(self.grad_options, **fields)
        if options == self.grad_options:
            return self
        other = self.fresh()
        other.grad_options = options
        other.m_grad = options.apply(self.m)
        other.mx = cast_floats(mjx.put_model(other.m_grad, device=local_device()), self.dtype)
        return other

    def fresh(self) -> Scene:
        """A shallow copy that compiles its own rollouts (none of this one's memoised ones)."""
        other = copy.copy(self)
        other._rollouts = {}
        return other

    def rollout_fn(self, horizon: int, **kwargs):
        """A compiled batched rollout of this scene; see `rollout.build_rollout`.

        Memoised per (horizon, options), so every caller shares one compiled
        function; jax.jit itself caches one executable per batch size.
        """
        key = (int(horizon), tuple(sorted(kwargs.items())))
        if key not in self._rollouts:
            self._rollouts[key] = build_rollout(self, horizon, **kwargs)
        return self._rollouts[key]
