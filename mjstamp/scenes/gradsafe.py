"""Gradient-safe patches for MJX's constraint solver (float32 reverse mode).

Reverse-mode gradients through ``mjx.step`` with contacts come back NaN in
float32 although every forward value is finite. The cause is always the same
pattern: a JVP rule whose *coefficient* is infinite (``1 / sqrt(0)`` in the
rule of ``sqrt``, ``y ** -2`` in the rule of ``x / y`` with a tiny ``y``) meets
a cotangent that is exactly zero (an inactive constraint row, a zero search
direction), and ``0 * inf = NaN`` then spreads through the whole rollout.
Float64 hides the division culprit (``y ** -2`` stops overflowing) but not
the elliptic-cone ``sqrt(0)``, which NaNs in any precision.

``patch_mjx()`` rewrites a handful of expressions inside
``mujoco.mjx._src.solver`` so that their *forward* value is computed by the
very same operation as before (bit-identical), while their JVP is evaluated
with the "double-where" trick: the infinite coefficient is never formed, and
the tangent is defined as 0 where the primal is degenerate.

Culprits patched (MJX 3.17.0 line numbers, ``mujoco/mjx/_src/solver.py``).
Ablation on the planar-billiards scene: #2 alone causes NaN in every config
with a hinge dof (pyramidal or elliptic, Newton or CG), #3 alone causes NaN in
every elliptic config *in float64 too*; #1 and #4 never produced a NaN on
their own here (#1 only feeds comparisons, so JAX prunes its tangent; it is
what ``checkify`` flags first though) and are patched defensively:

1. ``_linesearch`` L507: ``dmag = 2.0 * jp.sqrt(rows_0 * rows_2) + ...``.
   ``sqrt(0)`` whenever no constraint row is active. ``dmag`` only feeds the
   acceptance tolerance ``gtol_accept`` (a convergence heuristic used in
   comparisons), so it gets ``jax.lax.stop_gradient``.
2. ``_linesearch`` L521/L522/L572: the Newton steps
   ``alpha - deriv_0 / deriv_1``. ``deriv_1`` is the line-search curvature; it
   is tiny (but non-zero) when the search direction is ~0, e.g. at rest or for
   a small rotational inertia, so ``deriv_1 ** -2`` overflows in float32.
   Replaced by ``safe_div`` (tangent 0 when ``|deriv_1| <= mjMINVAL``).
3. ``_LSPoint.create`` L183 (elliptic cones): ``t = jp.sqrt(tsqr)`` with
   ``tsqr == 0`` for every inactive contact (its rows are zeroed), plus the
   divisions by ``t`` and ``tsqr`` (L202/L203). Replaced by ``safe_sqrt`` /
   ``safe_div``.
4. ``_update_constraint`` L327 (elliptic cones): ``force / (t + ...)`` where
   ``t`` may be tiny in the cone's middle zone. Replaced by ``safe_div``.
5. ``constraint._kbi`` L85 (any cone, any precision): the impedance's upper
   branch ``jp.power(1 - imp_x, power)`` is formed, then discarded by a
   ``where``, for rows deeper than the solimp width (``imp_x > 1``), where its
   base is negative: with a non-integer power (``solimp="... 1.5"``) its JVP
   coefficient is NaN. Found by ``tests/stress/fuzz.py`` (random solimp). The
   base is clamped at 0, which changes only the discarded values.

The rewrite is applied to the source text of the installed functions and each
target expression must be found exactly once, so an MJX upgrade that changes
these lines makes ``patch_mjx`` fail loudly instead of silently patching the
wrong thing.

Recommended options for gradient rollouts (found on planar billiards; the
numbers are in benchmarks/results/README.md, "Measurements quoted from the code"):

* ``opt.iterations = 1`` (required: reverse mode cannot go through the
  solver's ``while_loop``), ``opt.ls_iterations >= 4`` (``ls_iterations=1``
  leaves the single Newton step unconverged, and gradient norms explode).
* ``solver="Newton"``, ``cone="pyramidal"``: cheapest, and the condim-3
  pyramidal path needs only culprit #2 fixed. Elliptic cones need this patch
  in *any* precision.
* Contact ``solref="0.05 1"`` (timeconst >= 5 dt for dt = 0.01): a stiffer
  contact (the default 0.02) lets more long shots' gradient norms blow up.
  Add slide-joint ``damping`` ~0.05 (rolling-resistance proxy), which tames
  them further.
* ``patch_mjx()`` in either precision: float32 needs it on any contact,
  float64 for elliptic cones.

Typical use::

    from mjstamp.scenes import gradsafe
    gradsafe.patch_mjx()  # before the first jit trace of mjx.step
"""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Callable

import jax
import jax.numpy as jp
import mujoco

from mjstamp import _mjx

__all__ = ["GRADIENTS", "gradient_mode", "patch_mjx", "is_patched", "safe_div", "safe_sqrt"]

# N.B. mjMINVAL (1e-15) is MuJoCo's own "treat as zero" threshold; it is
# representable in float32, and 1 / mjMINVAL = 1e15 keeps every tangent
# coefficient below float32 overflow for cotangents up to ~1e23.
_FLOOR = mujoco.mjMINVAL

_PATCHED = False


@jax.custom_jvp
def safe_div(x: jax.Array, y: jax.Array) -> jax.Array:
    """Computes ``x / y`` with a gradient that is finite for tiny ``y``.

    The forward value is exactly ``x / y`` (same XLA op as plain division).
    The tangent is the usual ``(dx - (x / y) dy) / y`` where ``|y| > mjMINVAL``
    and 0 elsewhere, i.e. a degenerate quotient (its denominator has collapsed)
    is treated as locally constant.

    Args:
      x: numerator.
      y: denominator.

    Returns:
      ``x / y``.
    """
    return x / y


@safe_div.defjvp
def _safe_div_jvp(primals, tangents):
    x, y = primals
    dx, dy = tangents
    out = x / y
    ok = jp.abs(y) > _FLOOR
    # N.B. double-where: substitute a harmless denominator *before* dividing so
    # that neither the tangent nor its transpose ever holds 1/0 or y**-2 = inf;
    # a single where on the result would still give 0 * inf = NaN in reverse.
    y_ok = jp.where(ok, y, jp.ones_like(y))
    dout = jp.where(ok, (dx - out * dy) / y_ok, jp.zeros_like(out))
    return out, dout


@jax.custom_jvp
def safe_sqrt(x: jax.Array) -> jax.Array:
    """Computes ``sqrt(x)`` with a zero (not infinite) gradient at ``x <= 0``.

    Args:
      x: argument.

    Returns:
      ``jp.sqrt(x)`` (forward value unchanged, including NaN for ``x < 0``).
    """
    return jp.sqrt(x)


@safe_sqrt.defjvp
def _safe_sqrt_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    out = jp.sqrt(x)
    ok = x > 0
    # N.B. double-where, see _safe_div_jvp: 0.5 / sqrt(0) is never formed.
    s_ok = jp.sqrt(jp.where(ok, x, jp.ones_like(x)))
    dout = jp.where(ok, 0.5 * dx / s_ok, jp.zeros_like(out))
    return out, dout


# (function name, [(old expression, new expression), ...]). Every ``old`` must
# occur exactly once in the installed function's source.
_EDITS: dict[str, list[tuple[str, str]]] = {
    "_linesearch": [
        # Culprit 1: convergence heuristic, no meaningful gradient.
        (
            "dmag = 2.0 * jp.sqrt(rows_0 * rows_2) + jp.abs(quad_gauss[1])",
            "dmag = jax.lax.stop_gradient(2.0 * jp.sqrt(rows_0 * rows_2) + jp.abs(quad_gauss[1]))",
        ),
        # Culprit 2: Newton steps of the zoom line search.
        (
            "point_fn(lo.alpha - lo.deriv_0 / lo.deriv_1)",
            "point_fn(lo.alpha - _gs_safe_div(lo.deriv_0, lo.deriv_1))",
        ),
        (
            "point_fn(hi.alpha - hi.deriv_0 / hi.deriv_1)",
            "point_fn(hi.alpha - _gs_safe_div(hi.deriv_0, hi.deriv_1))",
        ),
        (
            "point_fn(p0.alpha - p0.deriv_0 / p0.deriv_1)",
            "point_fn(p0.alpha - _gs_safe_div(p0.deriv_0, p0.deriv_1))",
        ),
    ],
    "_LSPoint.create": [
        # Culprit 3: elliptic cone, tangential force norm of inactive contacts.
        ("t = jp.sqrt(tsqr)", "t = _gs_safe_sqrt(tsqr)"),
        (
            "t1 = (uv + alpha * vv) / t",
            "t1 = _gs_safe_div(uv + alpha * vv, t)",
        ),
        (
            "t2 = vv / t - (uv + alpha * vv) * t1 / tsqr",
            "t2 = _gs_safe_div(vv, t) - _gs_safe_div((uv + alpha * vv) * t1, tsqr)",
        ),
    ],
    "solve": [
        # Faithful gradients: the solver's main loop. Reverse mode cannot go through
        # `lax.while_loop`; MJX's own `_while_loop_scan` runs the same `cond`/`body`
        # for at most `opt.iterations` trips (no-ops once `cond` says done, as the
        # while_loop would stop), so forward values match and AD goes through.
        (
            "ctx = jax.lax.while_loop(cond, body, ctx)",
            "ctx = _while_loop_scan(cond, body, ctx, m.opt.iterations)",
        ),
    ],
    "_update_constraint": [
        # Culprit 4: elliptic cone, friction force direction.
        (
            "force_fri = -force / (t + ~middle_zone * mujoco.mjMINVAL)",
            "force_fri = _gs_safe_div(-force, t + ~middle_zone * mujoco.mjMINVAL)",
        ),
    ],
}

# The same, in ``mujoco.mjx._src.constraint``.
_CONSTRAINT_EDITS: dict[str, list[tuple[str, str]]] = {
    "_kbi": [
        # Culprit 5: impedance past the solimp width, a negative base to a
        # fractional power. N.B. `where(imp_x > 1.0, dmax, imp)` below discards
        # every value the clamp changes, so the forward pass is unchanged.
        (
            "jp.power(1 - imp_x, power)",
            "jp.power(jp.maximum(1 - imp_x, 0.0), power)",
        ),
    ],
}


def rewrite(module, qualname: str, edits: list[tuple[str, str]], *,
            extra: dict[str, object] | None = None) -> Callable:
    """`mjstamp._mjx.rewrite` with the two safe helpers (`_gs_safe_div`, `_gs_safe_sqrt`)."""
    helpers = {"_gs_safe_div": safe_div, "_gs_safe_sqrt": safe_sqrt}
    return _mjx.rewrite(module, qualname, edits, extra={**helpers, **(extra or {})})


GRADIENTS = ("unrolled", "implicit")
_MODE: contextvars.ContextVar[str] = contextvars.ContextVar("mjstamp_gradient", default="unrolled")
_SOLVERS: dict[str, Callable] = {}


@contextlib.contextmanager
def gradient_mode(mode: str):
    """How ``mjx.step`` calls traced inside this block differentiate the solver.

    ``"unrolled"``: the solver's own iterations, each one differentiated
    (``opt.iterations`` trips of a scan). ``"implicit"``: MJX's own converged
    solver, forward only, then one differentiated Newton step from its solution
    (see `_implicit_solve`). The mode is read when MJX is *traced*: wrap the
    Python code that calls ``mjx.step`` (a rollout's step function), not the
    call of a compiled function.
    """
    if mode not in GRADIENTS:
        raise ValueError(f"gradient mode {mode!r}; valid: {', '.join(GRADIENTS)}")
    token = _MODE.set(mode)
    try:
        yield
    finally:
        _MODE.reset(token)


def _implicit_solve(m, d):
    """MJX's converged solver in the forward pass; the implicit-function derivative.

    The solver finds qacc* minimising the convex constraint cost f(qacc; p),
    where p is everything `d` holds (M, J, aref, D, qfrc_smooth): ∇f(qacc*; p) = 0.
    Its derivative is dqacc*/dp = −H⁻¹ ∂∇f/∂p, H the Hessian of f at qacc* on the
    active set. One Newton step from the solution, qacc⁺ = qacc* − H⁻¹∇f(qacc*; p),
    evaluated with qacc* held constant, has exactly that derivative (∇f = 0 there,
    so the derivative of H⁻¹ does not enter). The forward value is qacc* itself:
    `straight` adds the step's tangent to it, not its value.

    N.B. why not unrolled iterations: under vmap every particle runs every trip
    of a fixed-count loop, and reverse mode stores each; this loop stops when the
    slowest particle has converged and reverse mode goes through one Newton step,
    as exact as several unrolled iterations at about the cost of one
    (`benchmarks/perf/gradient_modes.py`; see benchmarks/results/README.md).
    """
    from mujoco.mjx._src import solver  # pylint: disable=g-import-not-at-top

    if m.opt.solver != solver.SolverType.NEWTON:
        raise ValueError("the implicit gradient needs the Newton solver (its Hessian)")
    sg = jax.lax.stop_gradient
    d_star = _SOLVERS["while_loop"](m, jax.tree_util.tree_map(sg, d))
    q_star = d_star.qacc
    ctx = solver.Context.create(m, d.replace(qacc=q_star))
    q_new = q_star - ctx.Mgrad
    new = solver.Context.create(m, d.replace(qacc=q_new), grad=False)

    def straight(value, differentiable):
        return value + (differentiable - sg(differentiable))

    return d.tree_replace({
        "qacc": straight(q_star, q_new),
        "qfrc_constraint": straight(d_star.qfrc_constraint, new.qfrc_constraint),
        "_impl.efc_force": straight(d_star._impl.efc_force, new.efc_force),  # pylint: disable=protected-access
    })


def _solve(m, d):
    """`solver.solve` as patched: the mode of `gradient_mode` in force at trace time."""
    if _MODE.get() == "implicit":
        return _implicit_solve(m, d)
    return _SOLVERS["unrolled"](m, d)


def patch_mjx() -> None:
    """Patches MJX's solver so reverse-mode gradients exist and stay finite.

    Idempotent. Must run before the first ``jax.jit`` trace of ``mjx.step``
    (already-compiled functions keep the unpatched code). Forward values are
    MJX's own: each rewritten expression computes its primal with the same
    operation as before; only JVP rules differ, and only where the original
    rule was infinite; the solver's loop runs as a fixed-trip scan that no-ops
    once converged ("unrolled"), or as MJX's own while_loop with one
    differentiated Newton step after it ("implicit", see `gradient_mode`).

    Raises:
      RuntimeError: if the installed MJX no longer contains the expressions
        this patch was written against.
    """
    global _PATCHED
    if _PATCHED:
        return
    from mujoco.mjx._src import constraint, solver  # pylint: disable=g-import-not-at-top

    # Build everything first so a failed rewrite leaves MJX untouched.
    new = {q: rewrite(solver, q, e) for q, e in _EDITS.items()}
    kbi = rewrite(constraint, "_kbi", _CONSTRAINT_EDITS["_kbi"])
    constraint._kbi = kbi  # pylint: disable=protected-access
    solver._linesearch = new["_linesearch"]  # pylint: disable=protected-access
    solver._update_constraint = new["_update_constraint"]  # pylint: disable=protected-access
    solver._LSPoint.create = classmethod(new["_LSPoint.create"])  # pylint: disable=protected-access
    # N.B. the original `solve` calls the line search and constraint update through
    # the module's globals, so it uses the patched ones too.
    _SOLVERS["while_loop"] = solver.solve
    _SOLVERS["unrolled"] = new["solve"]
    solver.solve = _solve
    _PATCHED = True


def is_patched() -> bool:
    """Returns whether ``patch_mjx`` has been applied in this process."""
    return _PATCHED
