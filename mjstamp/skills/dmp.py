"""Goal-conditioned dynamic motion primitives (DMPs): fit from demonstrations, roll out in JAX.

The transformation system of STAMP eq. (5) (Pastor et al. 2009), in normalized
time u = t / τ so that one fitted DMP plays at any speed:

    v' = K (g − x) − D v − K (g − x₀) s + K f(s),    x' = v,    s' = −α s,
    f(s) = Σᵢ wᵢ ψᵢ(s) s / Σᵢ ψᵢ(s),    ψᵢ(s) = exp(−hᵢ (s − cᵢ)²),

where ' is d/du, v is the velocity in normalized time (τ ẋ) and the phase has
the closed form s(u) = exp(−α u). The centres cᵢ = exp(−α uᵢ) sit at evenly
spaced normalized times uᵢ ∈ [0, 1], and hᵢ = 1 / (cᵢ − cᵢ₊₁)² makes each
Gaussian fall to e⁻¹ at its neighbour.

Fitting is a linear regression: given a demonstration's x, x' and x'' (finite
differences in u), eq. (5) solved for f gives a target per sample, and w is the
ridge least-squares fit of those targets over all demonstrations stacked.

Frames. With ``frame="world"`` eq. (5) runs verbatim, per dimension: a forcing
term learnt for one displacement g − x₀ is replayed unchanged for another, so a
sideways bump stays sideways in *world* axes and the path distorts. With
``frame="planar_similarity"`` the DMP runs in canonical coordinates c, with
c(0) = 0 and world point x = x₀ + A c, where

    A = blockdiag([[Δx, −Δy], [Δy, Δx]], I_{dim−2}),    (Δx, Δy) = (g − x₀)[:2],

rotates and scales the plane so that canonical (1, 0) lands on the planar
displacement, and leaves the other dimensions (a height z, an angle) alone: a
10 cm lift stays 10 cm whatever the goal. The canonical goal is
(1, 0, (g − x₀)[2:]). A is linear in g − x₀ (no normalization), so rollouts are
smooth in x₀ and g, with finite gradients even at g = x₀ (where the planar
motion collapses onto x₀). Equivalently: eq. (5) in world coordinates with f
replaced by A f.

References:
  STAMP §III-C eq. (5) and §IV-C; P. Pastor, H. Hoffmann, T. Asfour, S. Schaal,
  "Learning and generalization of motor skills by learning from demonstration",
  ICRA 2009.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Sequence
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from mjstamp.errors import MjstampError, valid_list

__all__ = [
    "FRAMES",
    "MIN_RK4_STEPS",
    "DMP",
    "DMPConfig",
    "fit",
    "rollout",
]

FRAMES = ("world", "planar_similarity")

# N.B. the default K = 200 gives ω = √K ≈ 14 per unit of normalized time and
# α = 10 decays as fast; RK4 needs ω h well below its stability limit (≈ 2.8)
# to be accurate, so a rollout takes at least this many RK4 steps over its
# phase however few output samples `steps` asks for (h ≤ 0.01, ω h ≤ 0.15).
MIN_RK4_STEPS = 100


@dataclasses.dataclass(frozen=True)
class DMPConfig:
    """Static settings of a DMP: basis, gains, frame and integration.

    Attributes:
      n_basis: number of Gaussian basis functions ψᵢ of the forcing term.
      alpha: decay rate α of the phase s(u) = exp(−α u). The end of the phase
        misses g by about |Δ − Δ_demo| K e^{−α} / (√K − α)², Δ = g − x₀ (the
        −K (g − x₀) s term has not quite died out): 5e-4 |Δ − Δ_demo| with the
        defaults, 3e-3 with α = 8, K = 150 and 1e-2 with α = 6. In the planar
        dims of frame="planar_similarity" Δ is the demo's, so only the fit's
        own end error remains there.
      K: spring constant in normalized time (ω = √K ≈ 14, kept well above α:
        ω = α would resonate with the phase). An unforced reach's transient
        decays by (1 + ω) e^{−ω} ≈ 1e-5 within one phase.
      D: damping; None means critical damping 2√K (no overshoot of the goal).
      frame: "world" (eq. (5) verbatim) or "planar_similarity" (forcing rotated
        and scaled with the planar displacement; see the module docstring).
      substeps: RK4 steps per output sample of `rollout` (at least
        MIN_RK4_STEPS over the whole phase are taken regardless).

    References:
      STAMP eq. (5).
    """

    n_basis: int = 20
    alpha: float = 10.0
    K: float = 200.0
    D: float | None = None
    frame: str = "world"
    substeps: int = 4

    def __post_init__(self):
        if not isinstance(self.n_basis, int | np.integer) or self.n_basis < 2:
            raise MjstampError(f"DMPConfig n_basis={self.n_basis!r}: need an integer >= 2")
        for name in ("alpha", "K"):
            value = getattr(self, name)
            if not (isinstance(value, numbers.Real) and math.isfinite(value) and value > 0):
                raise MjstampError(f"DMPConfig {name}={value!r}: need a finite number > 0")
        if self.D is None:
            object.__setattr__(self, "D", 2.0 * math.sqrt(self.K))
        elif not (isinstance(self.D, numbers.Real) and math.isfinite(self.D) and self.D > 0):
            raise MjstampError(f"DMPConfig D={self.D!r}: need a finite number > 0, or None")
        if self.frame not in FRAMES:
            raise MjstampError(f"DMPConfig frame={self.frame!r}: valid: {valid_list(FRAMES)}")
        if not isinstance(self.substeps, int | np.integer) or self.substeps < 1:
            raise MjstampError(f"DMPConfig substeps={self.substeps!r}: need an integer >= 1")
        # Plain Python scalars: the config is hashed as static pytree metadata.
        for name in ("alpha", "K", "D"):
            object.__setattr__(self, name, float(getattr(self, name)))
        for name in ("n_basis", "substeps"):
            object.__setattr__(self, name, int(getattr(self, name)))


@partial(jax.tree_util.register_dataclass, data_fields=["weights"], meta_fields=["config"])
@dataclasses.dataclass(frozen=True, eq=False)
class DMP:
    """A fitted DMP (one skill): a pytree whose only leaf is `weights`.

    The config is static metadata, so `jax.grad` and `jax.vmap` see the weights
    alone, and DMPs of one config and shape stack leaf-wise with `jax.tree.map`.

    Attributes:
      weights: (n_basis, dim) array w of the forcing term f.
      config: the DMPConfig it was fitted with.

    References:
      STAMP eq. (5).
    """

    weights: jax.Array | np.ndarray
    config: DMPConfig

    @property
    def dim(self) -> int:
        """Number of dimensions of the motion (the last axis of `weights`)."""
        return int(np.shape(self.weights)[-1])

    @property
    def n_basis(self) -> int:
        """Number of basis functions (the first axis of `weights`)."""
        return int(np.shape(self.weights)[-2])


def _basis(config: DMPConfig, xp=np):
    """Centres c (n_basis,) and widths h (n_basis,) of the Gaussians ψᵢ in s."""
    c = np.exp(-config.alpha * np.linspace(0.0, 1.0, config.n_basis))
    gaps = -np.diff(c)
    h = 1.0 / np.append(gaps, gaps[-1]) ** 2
    return xp.asarray(c), xp.asarray(h)


def _features(s, c, h, xp):
    """ψᵢ(s) s / Σⱼ ψⱼ(s): (..., n_basis), via a softmax so Σψ never underflows."""
    logits = -h * (s[..., None] - c) ** 2
    if xp is np:
        logits = logits - logits.max(axis=-1, keepdims=True)
        psi = np.exp(logits)
        return psi / psi.sum(axis=-1, keepdims=True) * s[..., None]
    return jax.nn.softmax(logits, axis=-1) * s[..., None]


def _planar_block(delta2, xp):
    """[[Δx, −Δy], [Δy, Δx]] (..., 2, 2): canonical (1, 0) ↦ (Δx, Δy)."""
    dx, dy = delta2[..., 0], delta2[..., 1]
    return xp.stack([xp.stack([dx, -dy], -1), xp.stack([dy, dx], -1)], -2)


def fit(
    demos,
    duration: float | Sequence[float] = 1.0,
    config: DMPConfig | None = None,
    *,
    ridge: float = 1e-10,
) -> DMP:
    """Fits one DMP to m demonstrations of a skill by ridge least squares.

    Each demonstration goes from x₀ = its first sample to g = its last, with
    samples uniform over [0, duration]. It should start at rest (a rollout
    does) and end at rest (eq. (5) settles at g). The fit runs
    in normalized time u = t / duration, so the DMP does not depend on the
    durations: they are only checked (a DMP plays at any speed).

    Args:
      demos: (m, T, dim) array, or a sequence of m (T_k, dim) arrays (lengths
        may differ): positions over time.
      duration: seconds each demonstration lasts (one for all, or one per demo).
      config: DMPConfig; None means the defaults.
      ridge: Tikhonov weight λ relative to the mean diagonal of ΦᵀΦ; tiny, it
        only keeps basis functions the data barely excite from blowing up.

    Returns:
      The fitted DMP, weights (n_basis, dim) float64.

    Raises:
      MjstampError: demos not (m, T, dim), non-finite, dims differ, fewer than
        2·n_basis samples, duration ≤ 0, or (planar_similarity) a demo with no
        planar displacement or dim < 2.

    References:
      STAMP §III-C ("learning a DMP from demonstrations is a linear regression").
    """
    config = DMPConfig() if config is None else config
    demos = _check_demos(demos)
    durations = np.broadcast_to(np.asarray(duration, dtype=float), (len(demos),))
    bad = ~(np.isfinite(durations) & (durations > 0))
    if np.any(bad):
        raise MjstampError(f"DMP fit duration={duration!r}: need seconds > 0 for every demo")
    min_len = 2 * config.n_basis
    for k, x in enumerate(demos):
        if x.shape[0] < min_len:
            raise MjstampError(
                f"DMP fit demo {k} has {x.shape[0]} samples: need at least {min_len} "
                f"(2 x n_basis={config.n_basis}) to fit the basis"
            )
    dim = demos[0].shape[1]
    if config.frame == "planar_similarity":
        if dim < 2:
            raise MjstampError(
                f"DMP frame='planar_similarity' needs dim >= 2 (x, y first); demos have dim={dim}"
            )
        demos = [_to_canonical(x, k) for k, x in enumerate(demos)]

    c, h = _basis(config)
    rows, targets = [], []
    for x in demos:
        u_step = 1.0 / (x.shape[0] - 1)
        v = np.gradient(x, u_step, axis=0, edge_order=2)
        a = np.gradient(v, u_step, axis=0, edge_order=2)
        x0, g = x[0], x[-1]
        s = np.exp(-config.alpha * np.linspace(0.0, 1.0, x.shape[0]))
        # eq. (5) solved for f(s).
        targets.append((a + config.D * v) / config.K - (g - x) + (g - x0) * s[:, None])
        rows.append(_features(s, c, h, np))
    phi, target = np.concatenate(rows), np.concatenate(targets)
    gram = phi.T @ phi
    lam = ridge * np.trace(gram) / config.n_basis
    weights = np.linalg.solve(gram + lam * np.eye(config.n_basis), phi.T @ target)
    return DMP(weights=weights, config=config)


def _check_demos(demos) -> list[np.ndarray]:
    """Demos as a list of (T_k, dim) float64 arrays, or a one-line MjstampError."""
    if isinstance(demos, np.ndarray | jax.Array):
        arr = np.asarray(demos, dtype=float)
        if arr.ndim != 3:
            raise MjstampError(
                f"DMP fit demos have shape {arr.shape}: need (m, T, dim) "
                "(m demonstrations of T samples), or a list of (T, dim) arrays"
            )
        demos = list(arr)
    else:
        demos = [np.asarray(x, dtype=float) for x in demos]
        for k, x in enumerate(demos):
            if x.ndim != 2:
                raise MjstampError(f"DMP fit demo {k} has shape {x.shape}: need (T, dim)")
    if not demos:
        raise MjstampError("DMP fit got 0 demos: need at least one (T, dim) demonstration")
    dims = sorted({x.shape[1] for x in demos})
    if len(dims) > 1:
        raise MjstampError(f"DMP fit demos differ in dim ({dims}): one skill has one dim")
    if dims[0] < 1:
        raise MjstampError("DMP fit demos have dim 0: need at least one coordinate")
    for k, x in enumerate(demos):
        if not np.all(np.isfinite(x)):
            raise MjstampError(f"DMP fit demo {k} has non-finite positions (NaN or inf)")
    return demos


def _to_canonical(x: np.ndarray, k: int) -> np.ndarray:
    """A demo (T, dim) in its own canonical frame: c = A⁻¹ (x − x₀)."""
    rel = x - x[0]
    delta = rel[-1, :2]
    norm = float(np.hypot(*delta))
    excursion = float(np.max(np.hypot(rel[:, 0], rel[:, 1])))
    # N.B. A⁻¹ scales by 1/|Δ|: a demo that wanders far but ends near its start
    # would become a huge canonical path whose shape no new goal could use.
    if norm == 0.0 or excursion > 1e3 * norm:
        raise MjstampError(
            f"DMP frame='planar_similarity' demo {k} ends {norm:.3g} from its start in (x, y) "
            f"after moving up to {excursion:.3g}: it needs a planar displacement "
            "(use frame='world' for this skill)"
        )
    inv = _planar_block(delta, np).T / norm**2  # A⁻¹ = Aᵀ / |Δ|² for a rotation-scale
    out = rel.copy()
    out[:, :2] = rel[:, :2] @ inv.T
    return out


def rollout(
    params: DMP, x0, g, *, steps: int, duration: float | jax.Array = 1.0
) -> tuple[jax.Array, jax.Array]:
    """Integrates eq. (5) from x₀ at rest towards g over one phase (RK4, lax.scan).

    Differentiable w.r.t. x0, g, params.weights and duration; vmap it over
    batches of (x0, g). The same DMP played with another duration passes
    through the same positions at the same fractions of the duration.

    Args:
      params: a fitted DMP (weights (n_basis, dim)).
      x0: (dim,) start position.
      g: (dim,) goal position.
      steps: number of output intervals (a Python int >= 1).
      duration: seconds the phase lasts (τ), > 0.

    Returns:
      x: (steps+1, dim) positions at times linspace(0, duration, steps+1).
      v: (steps+1, dim) velocities in units per second (ẋ = v_normalized / τ).

    Raises:
      MjstampError: steps < 1, duration ≤ 0 (when concrete), or x0/g not (dim,).

    References:
      STAMP eq. (5) and §IV-C (a DMP turns a goal g_k into a trajectory).
    """
    if isinstance(steps, bool) or not isinstance(steps, int | np.integer) or steps < 1:
        raise MjstampError(f"DMP rollout steps={steps!r}: need an integer >= 1")
    if not isinstance(duration, jax.core.Tracer):
        d = np.asarray(duration)
        if d.shape != () or not (np.isfinite(d) and d > 0):
            raise MjstampError(f"DMP rollout duration={duration!r}: need seconds > 0")
    dim = params.dim
    for name, value in (("x0", x0), ("g", g)):
        if np.shape(value) != (dim,):
            raise MjstampError(
                f"DMP rollout {name} has shape {np.shape(value)}: need ({dim},) for this skill"
            )
    if params.config.frame == "planar_similarity" and dim < 2:
        raise MjstampError(f"DMP frame='planar_similarity' needs dim >= 2; this skill has {dim}")
    substeps = max(int(params.config.substeps), -(-MIN_RK4_STEPS // int(steps)))
    return _rollout(params, x0, g, duration, steps=int(steps), substeps=substeps)


@partial(jax.jit, static_argnames=("steps", "substeps"))
def _rollout(params: DMP, x0, g, duration, *, steps: int, substeps: int):
    cfg = params.config
    w = jnp.asarray(params.weights)
    dtype = jnp.result_type(w, jnp.asarray(x0), jnp.asarray(g), float)
    w = w.astype(dtype)
    x0, g = jnp.asarray(x0, dtype), jnp.asarray(g, dtype)
    c, h = _basis(cfg, jnp)
    c, h = c.astype(dtype), h.astype(dtype)

    delta = g - x0
    if cfg.frame == "planar_similarity":
        # Canonical coordinates: start 0, goal (1, 0, Δ[2:]); mapped back by A.
        start = jnp.zeros_like(x0)
        goal = delta.at[:2].set(jnp.array([1.0, 0.0], dtype))
    else:
        start, goal = x0, g

    def accel(u, x, v):
        s = jnp.exp(-cfg.alpha * u)
        f = _features(s, c, h, jnp) @ w
        return cfg.K * (goal - x) - cfg.D * v - cfg.K * (goal - start) * s + cfg.K * f

    du = 1.0 / (steps * substeps)

    def rk4(carry, _):
        u, x, v = carry
        k1x, k1v = v, accel(u, x, v)
        k2x, k2v = v + 0.5 * du * k1v, accel(u + 0.5 * du, x + 0.5 * du * k1x, v + 0.5 * du * k1v)
        k3x, k3v = v + 0.5 * du * k2v, accel(u + 0.5 * du, x + 0.5 * du * k2x, v + 0.5 * du * k2v)
        k4x, k4v = v + du * k3v, accel(u + du, x + du * k3x, v + du * k3v)
        x = x + du / 6.0 * (k1x + 2 * k2x + 2 * k3x + k4x)
        v = v + du / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v)
        return (u + du, x, v), None

    def output_step(carry, i):
        (_, x, v), _ = jax.lax.scan(rk4, carry, None, length=substeps)
        # N.B. restart u from the exact sample time: summing du drifts.
        carry = ((i + 1) / steps, x, v)
        return carry, (x, v)

    init = (jnp.zeros((), dtype), start, jnp.zeros_like(start))
    _, (xs, vs) = jax.lax.scan(output_step, init, jnp.arange(steps, dtype=dtype))
    xs = jnp.concatenate([start[None], xs])
    vs = jnp.concatenate([jnp.zeros_like(start)[None], vs])

    if cfg.frame == "planar_similarity":
        block = _planar_block(delta[:2], jnp)
        xs = jnp.concatenate([xs[:, :2] @ block.T, xs[:, 2:]], axis=1) + x0
        vs = jnp.concatenate([vs[:, :2] @ block.T, vs[:, 2:]], axis=1)
    return xs, vs / jnp.asarray(duration, dtype)
