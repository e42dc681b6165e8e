"""Solve settings (`SolveConfig`): nested by concern, validated once, unknown keys an error.

Kept apart from a task's own settings (`mjstamp.tasks`), as mujoco_playground
keeps an environment's config apart from its training config. The STAMP loop's
settings are the svgd engine's own `StampConfig` (one definition, one
validation); the other concerns are small frozen groups defined here.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import numbers
from collections.abc import Mapping
from typing import Any

from mjstamp import _moved
from mjstamp.errors import MjstampError, valid_list
from mjstamp.svgd.polish import PolishConfig
from mjstamp.svgd.stamp import StampConfig

#: Most particles a solve takes: the n x n kernel of 65536 in float64 is 32 GiB.
MAX_PARTICLES = 65536


class SettingDeprecationWarning(DeprecationWarning):
    """A solve setting given by its flat name of before the nesting (one line: old and new)."""


def _fail(name: str, value, what: str):
    raise MjstampError(f"solve setting {name}={value!r} must be {what}")


def _check_int(name: str, value, low: int, *, none: bool = False) -> None:
    if none and value is None:
        return
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low:
        _fail(name, value, f"an integer >= {low}" + " or None" * none)


def _check_real(name: str, value, low: float, high: float, *, open_low: bool,
                none: bool = False, what: str | None = None) -> None:
    if none and value is None:
        return
    ok = (not isinstance(value, bool) and isinstance(value, numbers.Real)
          and math.isfinite(value) and (value > low if open_low else value >= low)
          and value <= high)
    if not ok:
        _fail(name, value, what or f"a number > {low:g}" + " or None" * none)


def _check_bool(name: str, value) -> None:
    if not isinstance(value, bool):
        _fail(name, value, "True or False")


#: The solve's STAMP defaults (`run_stamp`'s are for a θ of unit scale): steps
#: and motion_tol relative to each task's box, iteration caps that keep a solve to minutes.
SOLVE_STAMP = StampConfig(svgd_learning_rate=None, sgd_learning_rate=None, svgd_max_iters=50,
                          sgd_max_iters=100, min_iters=20, motion_tol=None)


@dataclasses.dataclass(frozen=True)
class ScreenConfig:
    """Where the particles start and restart: a MuJoCo C screen of the prior (`mjstamp.seeding`).

    One group because all three read the screen: the candidates it replays, the
    re-draws placed near its successes, and β fitted to its costs.

    Attributes:
      candidates: seed the particles from `candidates · particles` draws of the
        prior replayed in MuJoCo C, spread over the task plans they reach; 1
        draws them from the prior directly. 64: a forward C replay costs a small
        fraction of STAMP's value and gradient, so 64 candidates per particle
        cost a few per cent of STAMP's 100+ iterations, and find rare task
        plans (billiards: all 16) that fewer candidates miss.
      rescue_near: share of the re-drawn particles (stall rescue and non-finite
        ones, `stamp.rescue_window`, `stamp.nonfinite_redraw`) placed near a
        success of the screen, with noise of `stamp.svgd_step` box widths, their
        task plan chosen uniformly among the screen's task plans
        (`seeding.Redraw`); the rest, and all when the screen found none, are
        drawn from the prior. In [0, 1].
      cost_scale: β, the inverse temperature of the posterior STAMP samples,
        log ρ = −β·C (and β·log p(Γ(θ)) for discrete SVGD's target; named apart
        from the soft indicators' β of `Task.contact`): a number > 0, or "auto":
        β = max(1, ln M / (median − min)) over the costs of the M candidates of
        the screen, so the best candidate stands at least ln M nats above the
        typical one. Costs written in metres (a distance to a goal) make a
        posterior so flat that SVGD's repulsion outweighs its driving term and
        spreads particles out of the valleys; "auto" sharpens such a posterior
        and leaves one already that steep as declared (billiards, pushing).
        Without a screen (`candidates` = 1), "auto" is 1. Reported costs are C
        itself, whatever β.
      seconds: 0, or screen on past `candidates · particles`, in chunks of
        fresh draws, until this much wall time has passed (a portfolio: the
        screen's share of the budget grows with it, and the solve returns
        every task plan the screen verified, `verify.keep_visited`). The
        number of candidates then depends on the machine's speed (the
        report's `screen.candidates`), so a rerun elsewhere may differ.
    """

    candidates: int = 64
    rescue_near: float = 0.5
    cost_scale: float | str = "auto"
    seconds: float = 0.0

    def __post_init__(self):
        _check_int("screen.candidates", self.candidates, 1)
        _check_real("screen.seconds", self.seconds, 0, math.inf, open_low=False,
                    what="a number of seconds >= 0")
        _check_real("screen.rescue_near", self.rescue_near, 0, 1, open_low=False,
                    what="a number in [0, 1]")
        scale = self.cost_scale
        if scale != "auto":
            _check_real("screen.cost_scale", scale, 0, math.inf, open_low=True,
                        what="a number > 0 or 'auto'")


@dataclasses.dataclass(frozen=True)
class CalibrationConfig:
    """How faithful the gradient model must be to the scene's physics before STAMP starts.

    One group because all four steer `scenes.fidelity.calibrate`.

    Attributes:
      enabled: pick the gradient solver's iterations so the MJX rollouts
        follow the scene's own physics (`scenes.fidelity.calibrate`).
      fidelity_tolerance: divergence allowed to 95% of the particles, metres;
        None: 1e-3 of the scene's size.
      max_solver_iterations: calibration budget (solver iterations); None: the
        MJCF's own `opt.iterations`.
      allow_unfaithful: solve even when no setting within budget is faithful
        (the result is then marked so).
    """

    enabled: bool = True
    fidelity_tolerance: float | None = None
    max_solver_iterations: int | None = None
    allow_unfaithful: bool = False

    def __post_init__(self):
        _check_bool("calibration.enabled", self.enabled)
        _check_real("calibration.fidelity_tolerance", self.fidelity_tolerance, 0, math.inf,
                    open_low=True, none=True)
        _check_int("calibration.max_solver_iterations", self.max_solver_iterations, 1,
                   none=True)
        _check_bool("calibration.allow_unfaithful", self.allow_unfaithful)


@dataclasses.dataclass(frozen=True)
class VerifyConfig:
    """What happens to the returned plans in MuJoCo C: which are kept, repaired and scored.

    One group because all five act after STAMP, on C replays of its particles.

    Attributes:
      repair: refine returned plans whose MuJoCo C replay fails, in C.
      repair_rounds: rounds of the local search per plan.
      repair_samples: candidates per plan and round.
      keep_visited: a particle whose final state is not a verified plan, or
        duplicates another's task plan, returns the plan it held at the end of
        SVGD or at the start if that one was, or else a success of the screen
        in a task plan no particle holds (no plan found is lost).
      robustness_samples: M perturbed MuJoCo C replays per verified plan under
        the task's uncertain physics (`Task.uncertain`, the defaults when it
        declared none), for its robustness score (`verify.robustness`); 0: no
        score. The same draws for every plan, seeded by the solve's seed.
    """

    repair: bool = True
    repair_rounds: int = 8
    repair_samples: int = 32
    keep_visited: bool = True
    robustness_samples: int = 32

    def __post_init__(self):
        _check_bool("verify.repair", self.repair)
        _check_int("verify.repair_rounds", self.repair_rounds, 0)
        _check_int("verify.repair_samples", self.repair_samples, 1)
        _check_bool("verify.keep_visited", self.keep_visited)
        _check_int("verify.robustness_samples", self.robustness_samples, 0)


@dataclasses.dataclass(frozen=True)
class RobustConfig:
    """Planning for uncertain physics: the objective STAMP minimises over draws of it.

    Its own group because, unlike `verify.robustness_samples` (a score measured
    afterwards), it changes what STAMP optimises and what each iteration costs.

    Attributes:
      draws: every particle is rolled out in K = `draws` draws of the task's
        uncertainty (`Problem.with_robust`; the same draws throughout the solve,
        seeded by its seed and apart from the score's), and STAMP minimises the
        expected cost over them (or its CVaR, `cvar`); each iteration costs
        about K times as much. 0: plan for the nominal model. `mjstamp solve
        --robust` sets 8.
      cvar: with `draws`, the share of the worst draws whose mean cost is
        minimised (CVaR at that level), in (0, 1]; 1: the expected cost.
      select: 0, or after verification each verified task plan's particles
        take the most robust of their own plans and up to `select` of the
        screen's successes in that task plan, all scored on
        `verify.robustness_samples` (at least 32) perturbed MuJoCo C replays of
        draws apart from both the score's and the planning's (`SELECT_STREAM`),
        so the score stays an honest estimate. It costs that many C replays per
        candidate, no MJX work. `mjstamp solve --robust` sets 64.
    """

    draws: int = 0
    cvar: float = 1.0
    select: int = 0

    def __post_init__(self):
        _check_int("robust.draws", self.draws, 0)
        _check_int("robust.select", self.select, 0)
        _check_real("robust.cvar", self.cvar, 0, 1, open_low=True,
                    what="a number in (0, 1]: the share of the worst draws averaged "
                         "(1: the expected cost)")


@dataclasses.dataclass(frozen=True)
class LandingConfig:
    """Gauss–Newton in MuJoCo C on the task's residual goals (`verify.land`).

    Its own group because it runs on the scene's own physics, not the gradient
    model: where a scene's outcome is rough at fine scales (contacts on a step
    grid), the exact derivative predicts nothing at a step's scale and the
    polish in the gradient model (`polish`) crawls; central differences in C at
    the step's own scale do not, and C rollouts are cheap. Idle where the task
    declares no residual costs.

    Attributes:
      iterations: most iterations per particle after STAMP and its polish
        (each 2k + 1 C rollouts, k the movable coordinates); 0: off.
      early: also land the screen's chosen candidates (its successes and
        nearest misses, spread over task plans) before STAMP starts; the
        plans they verify are returned where no particle holds their task
        plan (`verify.keep_visited`), and the first verified plan comes from
        the screen and one landing rather than the end of the solve.
      radius: initial trust radius, in box widths.
      depth: a plan has landed within this share of each goal's tolerance.
      sgd_max_iters: where the landing runs, the SGD phase stops after at
        most this many iterations: Gauss–Newton refines in its place (Adam at
        a fixed step circles an optimum at its step's scale); None: as
        `stamp.sgd_max_iters`.
    """

    iterations: int = 20
    early: bool = True
    radius: float = 0.01
    depth: float = 0.25
    sgd_max_iters: int | None = 20

    def __post_init__(self):
        _check_int("landing.iterations", self.iterations, 0)
        _check_bool("landing.early", self.early)
        _check_real("landing.radius", self.radius, 0, 1, open_low=True,
                    what="a number in (0, 1] (box widths)")
        _check_real("landing.depth", self.depth, 0, 1, open_low=True,
                    what="a number in (0, 1] (a share of the goal's tolerance)")
        _check_int("landing.sgd_max_iters", self.sgd_max_iters, 0, none=True)


#: Each group's class and its default, in `SolveConfig`'s order.
_GROUPS = {"stamp": (StampConfig, SOLVE_STAMP), "screen": (ScreenConfig, ScreenConfig()),
           "calibration": (CalibrationConfig, CalibrationConfig()),
           "polish": (PolishConfig, PolishConfig()), "landing": (LandingConfig, LandingConfig()),
           "verify": (VerifyConfig, VerifyConfig()), "robust": (RobustConfig, RobustConfig())}

#: The flat names of before the nesting (deprecated, kept one release) -> the nested ones.
FLAT_NAMES = {
    **{name: f"stamp.{name}" for name in (
        "svgd_max_iters", "sgd_max_iters", "min_iters", "window", "rtol", "motion_tol",
        "svgd_learning_rate", "sgd_learning_rate", "svgd_step", "sgd_step", "jacobian",
        "rescue_window", "nonfinite_redraw", "backtrack")},
    "calibrate": "calibration.enabled",
    **{name: f"calibration.{name}" for name in (
        "fidelity_tolerance", "max_solver_iterations", "allow_unfaithful")},
    **{name: f"verify.{name}" for name in (
        "repair", "repair_rounds", "repair_samples", "keep_visited", "robustness_samples")},
    "screen": "screen.candidates", "rescue_near": "screen.rescue_near",
    "cost_scale": "screen.cost_scale", "robust": "robust.draws", "robust_cvar": "robust.cvar",
}


def _deprecated(old: str, new: str) -> None:
    """Warns where the user wrote the flat name (`_moved.warn_at_user`)."""
    _moved.warn_at_user(f"solve setting {old!r} is now {new!r}; the flat name goes in the next "
                        "release", SettingDeprecationWarning)



def _is_group_value(name: str, value) -> bool:
    """Whether `value` given for `name` is a group (or its dict), not a flat setting's value."""
    return name in _GROUPS and (value is None or isinstance(value, (Mapping, _GROUPS[name][0])))


@dataclasses.dataclass(frozen=True, init=False)
class SolveConfig:
    """Settings of `solve`, nested by concern and validated on construction.

    `SolveConfig(particles, devices, stamp=StampConfig(...), screen=ScreenConfig(...),
    calibration=..., verify=..., robust=...)`; a group may also be given as a
    dict of its fields, laid over the solve's defaults for it (`stamp={"backtrack":
    False}`). Defaults are meant to work on a task nobody tuned: step sizes follow
    each variable's box, iteration caps keep a solve to minutes, and the gradient
    model is calibrated against the scene's own physics before STAMP starts.

    The flat names of before the nesting (`SolveConfig(backtrack=False)`, every
    key of `FLAT_NAMES`) still work for one release, each with one
    `SettingDeprecationWarning` naming the old and the new name.

    Attributes:
      particles: n >= 2 particles (candidate plans).
      budget: None, or the solve's wall time in seconds, as a portfolio: the
        C screen runs on in chunks while they still find new task plans (up to
        a third of the budget, `seeding.screen_particles`' `until_dry`), then
        SVGD and SGD share what is left but a fifth (kept for the polish, the
        landing and verification) in the ratio of their iteration caps, each
        phase ending at its deadline (the landing and checks after STAMP
        are not cut short: the fifth is their estimate, not a limit). The
        plans then depend on the machine's speed; None (the default) keeps a
        seed's plans the same everywhere.
      devices: shard the particles' rollouts over this many devices
        (`mjstamp.parallel`): host devices on a CPU (`mjstamp.configure(devices=N)`
        first), local GPUs on a GPU machine; None: every device JAX sees. The
        plans do not depend on it beyond rounding (see the README).
      stamp: the STAMP loop (`svgd.StampConfig`, documented there). The solve's
        defaults (`SOLVE_STAMP`) differ from `run_stamp`'s: svgd_max_iters 50,
        sgd_max_iters 100, min_iters 20; learning rates None, so each phase's
        Adam step is `svgd_step` / `sgd_step` of each coordinate's box width;
        motion_tol None: 1e-4 of the mean box width. Its seed is the solve's
        (`solve(seed=...)`) and stays 0 here; its learning rates are numbers or
        None (a schedule goes to `svgd.run_stamp` itself).
      screen: where the particles start and restart (`ScreenConfig`).
      calibration: the gradient model's fidelity check (`CalibrationConfig`).
      polish: after STAMP, Levenberg–Marquardt on the task's residual costs
        in the gradient model (`svgd.PolishConfig`); `max_iters` None (the
        default): 20 on an accelerator, off on a CPU (`solve.polish_iterations`);
        idle where the task declares no residuals.
      landing: Gauss–Newton on the same residuals in MuJoCo C, before STAMP
        (the screen's candidates) and after the polish (`LandingConfig`).
      verify: the returned plans in MuJoCo C (`VerifyConfig`).
      robust: planning for uncertain physics (`RobustConfig`).
    """

    particles: int = 128
    devices: int | None = None
    budget: float | None = None
    stamp: StampConfig = SOLVE_STAMP
    screen: ScreenConfig = ScreenConfig()
    calibration: CalibrationConfig = CalibrationConfig()
    polish: PolishConfig = PolishConfig()
    landing: LandingConfig = LandingConfig()
    verify: VerifyConfig = VerifyConfig()
    robust: RobustConfig = RobustConfig()

    def __init__(self, particles: int = 128, devices: int | None = None, *,
                 budget: float | None = None, stamp=None,
                 screen=None, calibration=None, polish=None, landing=None, verify=None,
                 robust=None, **flat):
        given = {"stamp": stamp, "screen": screen, "calibration": calibration,
                 "polish": polish, "landing": landing, "verify": verify, "robust": robust}
        changes = {name: {} for name in _GROUPS}
        for name, value in list(given.items()):
            if not _is_group_value(name, value):  # the flat `screen=1`, `robust=8`
                flat = {name: value, **flat}
                given[name] = None
        for old, value in flat.items():
            if old not in FLAT_NAMES:
                raise TypeError(f"SolveConfig got an unexpected keyword argument {old!r}")
            _deprecated(old, FLAT_NAMES[old])
            group, field = FLAT_NAMES[old].split(".")
            changes[group][field] = value
        object.__setattr__(self, "particles", particles)
        object.__setattr__(self, "devices", devices)
        object.__setattr__(self, "budget", budget)
        for name, (_, default) in _GROUPS.items():
            value = given[name]
            if isinstance(value, Mapping):
                changes[name] = {**value, **changes[name]}
                value = None
            object.__setattr__(self, name, _group(name, value or default, changes[name]))
        self._validate()

    def _validate(self):
        _check_int("particles", self.particles, 2)
        if self.particles > MAX_PARTICLES:
            raise MjstampError(
                f"solve setting particles={self.particles} must be at most {MAX_PARTICLES}: the "
                f"n x n kernel of {self.particles} particles needs "
                f"{self.particles**2 * 8 / 2**30:.3g} GiB in float64"
            )
        _check_int("devices", self.devices, 1, none=True)
        _check_real("budget", self.budget, 0, math.inf, open_low=True, none=True,
                    what="a number of seconds > 0 or None")
        for name in ("svgd_learning_rate", "sgd_learning_rate"):
            if callable(getattr(self.stamp, name)):
                raise MjstampError(f"solve setting stamp.{name} must be a number > 0 or None "
                                   "(a schedule goes to svgd.run_stamp itself)")
        if self.stamp.seed != 0:
            raise MjstampError(f"solve setting stamp.seed={self.stamp.seed!r}: a solve's seed "
                               "is solve(seed=...) (--seed); leave stamp.seed at 0")

    @classmethod
    def fields(cls) -> list[str]:
        """Every setting's key as `from_dict` and `--set` take it: "stamp.backtrack"..."""
        return list(cls.leaves())

    @staticmethod
    def groups() -> list[str]:
        """Names of the groups ("stamp", "screen", "calibration", "polish", "landing", ...)."""
        return list(_GROUPS)

    @classmethod
    def leaves(cls) -> dict[str, tuple[Any, str]]:
        """{dotted key: (its default in a solve, its annotation)}, in the order of the groups."""
        out = {"particles": (128, "int"), "devices": (None, "int | None"),
               "budget": (None, "float | None")}
        for name, (group_cls, default) in _GROUPS.items():
            for f in dataclasses.fields(group_cls):
                if not (name == "stamp" and f.name == "seed"):
                    out[f"{name}.{f.name}"] = (getattr(default, f.name), str(f.type))
        return out

    @classmethod
    def from_dict(cls, config: Mapping[str, Any] | None, *, ignore=(),
                  base: SolveConfig | None = None) -> SolveConfig:
        """Builds a config from a dict; keys in `ignore` (a task's own settings) are skipped.

        Keys are "particles", "devices", a group with a dict of its fields
        (`{"stamp": {"backtrack": False}}`) or a dotted key (`{"stamp.backtrack":
        False}`), later keys over earlier ones; the flat names of before the
        nesting (`FLAT_NAMES`) work with a `SettingDeprecationWarning`.

        Args:
          config: the settings to change.
          ignore: keys to skip.
          base: the settings changed (default: `SolveConfig()`).

        Raises:
          MjstampError: a key that is neither a solve setting nor in `ignore`,
            naming it, the closest valid key and every valid one; a bad value,
            naming the setting by its dotted key.
        """
        valid = cls.fields()
        settings = {}
        for key, value in dict(config or {}).items():
            if key in ignore:
                continue
            if _is_group_value(key, value) and isinstance(value, Mapping):
                settings.update({f"{key}.{k}": v for k, v in value.items()})
            elif key in FLAT_NAMES and key not in valid:
                _deprecated(key, FLAT_NAMES[key])
                settings[FLAT_NAMES[key]] = value
            elif key in _GROUPS and isinstance(value, _GROUPS[key][0]):
                settings.update({f"{key}.{k}": v for k, v in
                                 _group_dict(key, value).items()})
            else:
                settings[key] = value
        for key in settings:
            if key not in valid:
                options = valid + sorted(ignore)
                hint = _did_you_mean(str(key), options)
                raise MjstampError(f"unknown solve setting {key!r}{hint}; valid: "
                                   f"{valid_list(options, limit=60)}")
        base = base or cls()
        top = {k: settings.get(k, getattr(base, k)) for k in ("particles", "devices", "budget")}
        groups = {name: {k.split(".", 1)[1]: v for k, v in settings.items()
                         if k.startswith(name + ".")} for name in _GROUPS}
        return cls(**top, **{name: _group(name, getattr(base, name), changes)
                             for name, changes in groups.items()})

    def __getattr__(self, name: str):
        """`cfg.backtrack` (a flat name) reads `cfg.stamp.backtrack`, with the deprecation notice.

        N.B. `screen` and `robust` are groups now: `cfg.screen.candidates`, `cfg.robust.draws`.
        """
        new = FLAT_NAMES.get(name)
        if new is None or name in _GROUPS:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        _deprecated(name, new)
        group, field = new.split(".")
        return getattr(getattr(self, group), field)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready view, nested like the config ({"particles", "devices", "stamp": {...}})."""
        return {"particles": self.particles, "devices": self.devices, "budget": self.budget,
                **{name: _group_dict(name, getattr(self, name)) for name in _GROUPS}}

    def flat_dict(self) -> dict[str, Any]:
        """The flat view of before the nesting ({"particles", "svgd_max_iters", ...}).

        Checkpoints hash it (`solve._checkpointing`), so one written before the
        nesting still resumes.
        """
        flat = {old: getattr(getattr(self, new.split(".")[0]), new.split(".")[1])
                for old, new in FLAT_NAMES.items()}
        out = {"particles": self.particles, **flat, "devices": self.devices}
        if self.budget is not None:  # N.B. only when set: earlier checkpoints keep their key
            out["budget"] = self.budget
        return out


def _did_you_mean(key: str, options: list[str]) -> str:
    """' (did you mean 'stamp.svgd_max_iters'?)' for "svgd_iters": a key's last part counts too."""
    by_last = {option.rsplit(".", 1)[-1]: option for option in reversed(options)}
    close = difflib.get_close_matches(key, options, n=1)
    if not close:
        close = [by_last[m] for m in difflib.get_close_matches(key.rsplit(".", 1)[-1],
                                                                list(by_last), n=1)]
    return f" (did you mean {close[0]!r}?)" if close else ""


def _group(name: str, value, changes: Mapping[str, Any]):
    """Group `name` as given (`value`), with `changes` laid over it; errors name "name.field"."""
    if not changes:
        return value
    cls = _GROUPS[name][0]
    known = [f.name for f in dataclasses.fields(cls)]
    for key in changes:
        if key not in known:
            options = [f"{name}.{k}" for k in known]
            hint = _did_you_mean(f"{name}.{key}", options)
            raise MjstampError(f"unknown solve setting {name + '.' + str(key)!r}{hint}; "
                               f"valid: {valid_list(options)}")
    try:
        return dataclasses.replace(value, **changes)
    except MjstampError as e:
        if name != "stamp":  # the others name their settings with the group already
            raise
        raise MjstampError(f"solve setting stamp.{e}") from None


def _group_dict(name: str, value) -> dict[str, Any]:
    out = dataclasses.asdict(value)
    if name == "stamp":
        out.pop("seed")  # N.B. the solve's own seed (`solve(seed=...)`)
    return out
