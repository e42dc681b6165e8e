"""Positive definite kernels for SVGD, with their Stein repulsion in closed form.

A kernel here is a static description (which coordinates, which bandwidths); its
`evaluate` takes the current particles and returns, in one pass,

  * the Gram matrix K[j, i] = k(x_j, x_i), shape (n, n);
  * the weighted repulsion R[i] = Σ_j a_j ∇_{x_j} k(x_j, x_i), shape (n, D),
    the second term of the SVGD update (STAMP eq. (1), (4));
  * the bandwidths used (median heuristic or fixed), for diagnostics.

RBF and von Mises kernels compute R with matrix products (O(n² D) flops and
O(n²) memory, no (n, n, D) tensor). A kernel may also see the particles through
a differentiable feature map ψ(θ) = [θ, φ(θ)]: `evaluate` then takes the
per-particle Jacobians J = ∂ψ/∂θ, shape (n, D, d), and returns R in θ-space,
R[i] = Σ_j a_j J_jᵀ ∇₁k₀(ψ_j, ψ_i), so the repulsion includes the gradient
through φ (App. B-C).

Bandwidths follow App. B-C: k(x, y) = exp(−Σ_g ‖x_g − y_g‖² / s_g²) with one
bandwidth s_g per group of coordinates, and the median heuristic
s_g = median_{i<j} ‖x_{i,g} − x_{j,g}‖ / √(log n) (Liu & Wang, 2016). The
bandwidth is treated as a constant of each step (no gradient flows through it).

References:
  STAMP eq. (1) and (4) (SVGD, discrete SVGD); App. B-C (RBF over [θ, w(θ)]
  with a bandwidth per block, median heuristic); App. C-B (weighted sum of RBF
  and von Mises kernels over parts of θ).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from mjstamp.svgd._checks import check_particles
from mjstamp.svgd._jacobian import JacobianMode, check_mode, value_and_batched_jacobian

__all__ = [
    "Kernel",
    "KernelTerms",
    "RBF",
    "VonMises",
    "SumKernel",
    "FeatureKernel",
    "rbf",
    "von_mises",
    "sum_kernels",
    "feature_kernel",
    "median_bandwidth",
    "flat_bandwidths",
]

IndexSpec = slice | Sequence[int]
Bandwidth = float | str  # a positive float, or "median"


class KernelTerms(NamedTuple):
    """What one kernel evaluation returns.

    Attributes:
      gram: (n, n) Gram matrix, gram[j, i] = k(x_j, x_i).
      repulsion: (n, D) or, when a Jacobian was given, (n, d) array;
        repulsion[i] = Σ_j a_j ∇_{x_j} k(x_j, x_i).
      params: pytree of the bandwidths used (one array of shape (g,) per
        RBF / von Mises kernel, nested like the kernel).
    """

    gram: jax.Array
    repulsion: jax.Array
    params: Any


def flat_bandwidths(params: Any) -> jax.Array:
    """Concatenates the bandwidths of a `KernelTerms.params` pytree, shape (g,)."""
    leaves = [jnp.ravel(p) for p in jax.tree.leaves(params)]
    return jnp.concatenate(leaves) if leaves else jnp.zeros((0,))


# ----------------------------------------------------------------------------
# Index and bandwidth specs: validated when a kernel is built, resolved against
# the dimension when it is evaluated (dimensions are static under jit).


def _check_spec(spec: Any, what: str) -> None:
    if isinstance(spec, slice):
        return
    if isinstance(spec, (str, bytes)) or not isinstance(
        spec, (Sequence, range, np.ndarray)
    ):
        raise ValueError(f"{what} must be a slice or a sequence of ints; got {spec!r}")
    if not all(isinstance(i, (int, np.integer)) for i in spec):
        raise ValueError(f"{what} must be a slice or a sequence of ints; got {spec!r}")
    if len(spec) == 0:
        raise ValueError(f"{what} must select at least one coordinate; got {spec!r}")


def _resolve(spec: IndexSpec, dim: int, what: str) -> np.ndarray:
    if isinstance(spec, slice):
        idx = np.arange(dim)[spec]
    else:
        idx = np.asarray(spec, dtype=int)
        bad = idx[(idx < 0) | (idx >= dim)]
        if bad.size:
            raise ValueError(
                f"{what} selects coordinates {bad.tolist()}, outside the valid "
                f"range [0, {dim}) of this {dim}-dimensional input"
            )
    if idx.size == 0:
        raise ValueError(f"{what} selects no coordinate of the {dim}-dimensional input")
    return idx


def _take(x: jax.Array, idx: np.ndarray) -> jax.Array:
    """x[..., idx] along axis 1, as a slice when idx is contiguous (no gather)."""
    if idx.size and np.array_equal(idx, np.arange(idx[0], idx[0] + idx.size)):
        return x[:, idx[0] : idx[0] + idx.size]
    return x[:, idx]


def _check_cover(index_sets: Sequence[np.ndarray], dim: int, what: str, *, once: bool):
    counts = np.zeros(dim, dtype=int)
    for idx in index_sets:
        np.add.at(counts, idx, 1)
    missing = np.flatnonzero(counts == 0)
    if missing.size:
        raise ValueError(
            f"{what} must cover every coordinate 0..{dim - 1} of the "
            f"{dim}-dimensional input; coordinates {missing.tolist()} are in none"
        )
    if once:
        twice = np.flatnonzero(counts > 1)
        if twice.size:
            raise ValueError(
                f"{what} must hold each coordinate once; coordinates "
                f"{twice.tolist()} are in more than one group"
            )


def _check_bandwidth(
    bandwidth: Any, n_groups: int | None
) -> tuple[Bandwidth, ...] | Bandwidth:
    def one(b):
        if isinstance(b, str):
            if b != "median":
                raise ValueError(f"bandwidth must be > 0 or 'median'; got {b!r}")
            return b
        try:
            value = float(b)
        except (TypeError, ValueError):
            raise ValueError(f"bandwidth must be > 0 or 'median'; got {b!r}") from None
        if not (value > 0 and math.isfinite(value)):
            raise ValueError(f"bandwidth must be > 0 (finite) or 'median'; got {b!r}")
        return value

    if isinstance(bandwidth, (str, int, float, np.floating, np.integer)):
        return one(bandwidth)
    values = tuple(one(b) for b in bandwidth)
    if n_groups is not None and len(values) != n_groups:
        raise ValueError(
            f"bandwidth must be one value or one per group ({n_groups}); "
            f"got {len(values)} values"
        )
    return values


# ----------------------------------------------------------------------------
# Dense helpers


def _sqdist(z: jax.Array) -> jax.Array:
    """Pairwise squared distances of rows of a centred z, (n, n), zero diagonal."""
    sq = jnp.sum(z * z, axis=1)
    d2 = sq[:, None] + sq[None, :] - 2.0 * (z @ z.T)
    # N.B. the expansion can round to tiny negatives, and k(x, x) must be 1.
    d2 = jnp.maximum(d2, 0.0)
    return d2 * (1.0 - jnp.eye(z.shape[0], dtype=z.dtype))


def median_pairwise_distance(d2: jax.Array, valid: jax.Array | None = None) -> jax.Array:
    """median_{i<j} √d2_ij, exactly, from a symmetric (n, n) d2 with zero diagonal.

    With `valid` ((n,) bool), only pairs of valid particles count.

    Sorting the n(n−1)/2 distances costs ~180 ms per step at n = 1000 on a CPU;
    this bisects on the bit patterns of d2 instead (non-negative floats order
    like their bits): one counting pass over d2 per bit, ~8x faster.
    """
    n = d2.shape[0]
    itype = {4: jnp.int32, 8: jnp.int64}[d2.dtype.itemsize]
    bits = jax.lax.bitcast_convert_type(d2, itype)
    if valid is None:
        m = n * (n - 1) // 2
        pairs = None

        def count_le(t):  # off-diagonal entries <= t; the n diagonal zeros always are
            return jnp.sum(bits <= t) - n
    else:
        nv = jnp.sum(valid.astype(itype))
        m = nv * (nv - 1) // 2
        pairs = valid[:, None] & valid[None, :] & ~jnp.eye(n, dtype=bool)

        def count_le(t):  # off-diagonal entries of valid pairs <= t
            return jnp.sum(pairs & (bits <= t))

    # The off-diagonal entries hold every pair twice; the median of that doubled
    # set is the median over i<j: the mean of its order statistics m−1 and m.
    def bisect(_, bounds):
        lo, hi = bounds
        mid = lo + (hi - lo) // 2
        enough = count_le(mid) >= m
        return jnp.where(enough, lo, mid + 1), jnp.where(enough, mid, hi)

    nbits = 8 * d2.dtype.itemsize
    top = jnp.max(bits) if pairs is None else jnp.max(jnp.where(pairs, bits, 0))
    _, hi = jax.lax.fori_loop(0, nbits, bisect, (jnp.zeros((), itype), top))
    lower = jax.lax.bitcast_convert_type(hi, d2.dtype)
    above = bits > hi if pairs is None else pairs & (bits > hi)
    upper = jnp.where(count_le(hi) >= m + 1, lower, jnp.min(jnp.where(above, d2, jnp.inf)))
    return 0.5 * (jnp.sqrt(lower) + jnp.sqrt(upper))


def _median_bandwidth_from_sqdist(d2: jax.Array, valid: jax.Array | None = None) -> jax.Array:
    """Median heuristic s = median_{i<j} dist_ij / √(log n) from squared distances.

    With `valid` ((n,) bool), over the valid particles only (n: how many).
    """
    n = d2.shape[0]
    # No gradient flows through the bandwidth (and none into the bisection).
    med = median_pairwise_distance(jax.lax.stop_gradient(d2), valid)
    # N.B. divided by a Python constant, as before masks existed: XLA turns that into a
    # multiply, a division by a traced scale would round differently.
    full = med / math.sqrt(math.log(n))
    if valid is not None:
        nv = jnp.sum(valid).astype(d2.dtype)
        masked = med / jnp.sqrt(jnp.log(jnp.maximum(nv, 2.0)))
        full = jnp.where(nv == n, full, masked)
        med = jnp.where(nv >= 2, med, 0.0)
    # N.B. when most particles of a group coincide the median is 0; any positive
    # bandwidth gives coincident particles zero repulsion, so fall back to 1.
    return jnp.where(med > 0, full, 1.0)


def _mean_rows(x: jax.Array, valid: jax.Array | None) -> jax.Array:
    """(D,) mean of the rows of x, of the valid ones when a mask is given."""
    if valid is None:
        return jnp.mean(x, axis=0)
    count = jnp.maximum(jnp.sum(valid), 1).astype(x.dtype)
    masked = jnp.sum(jnp.where(valid[:, None], x, 0.0), axis=0) / count
    # N.B. jnp.mean's own bits when every row is valid (results stay bit-identical).
    return jnp.where(jnp.all(valid), jnp.mean(x, axis=0), masked)


def _separable_repulsion(
    kw: jax.Array,
    terms: Sequence[tuple[jax.Array, jax.Array | None]],
    jac: jax.Array | None,
) -> jax.Array:
    """Σ_j kw_ji J_jᵀ g_ji for a pairwise gradient g_ji = Σ_r A_r[j] ⊙ B_r[i].

    Args:
      kw: (n, n) weighted Gram matrix, kw[j, i] = a_j k(x_j, x_i).
      terms: pairs (A, B): A is (n, D), or (D,) when constant over j; B is (n, D),
        or None for ones.
      jac: None (J = identity, result (n, D)) or (n, D, d) (result (n, d)).

    Returns:
      (n, D) or (n, d) array.
    """
    out = 0.0
    colsum = None
    n = kw.shape[0]
    for a, b in terms:
        if jac is None:
            if a.ndim == 1:
                colsum = jnp.sum(kw, axis=0) if colsum is None else colsum
                r = colsum[:, None] * a[None, :]
            else:
                r = kw.T @ a
            out = out + (r if b is None else r * b)
        else:
            d_out = jac.shape[-1]
            if b is None:  # contract over D before the n×n product: O(n² d)
                u = jnp.einsum("jD,jDd->jd", jnp.broadcast_to(a, jac.shape[:2]), jac)
                out = out + kw.T @ u
            else:
                aj = jac * (a[None, :, None] if a.ndim == 1 else a[:, :, None])
                m = (kw.T @ aj.reshape(n, -1)).reshape(n, -1, d_out)
                out = out + jnp.einsum("iDd,iD->id", m, b)
    return out


def _uniform_weights(n: int, dtype) -> jax.Array:
    return jnp.full((n,), 1.0 / n, dtype=dtype)


# ----------------------------------------------------------------------------
# Kernels


class Kernel:
    """Base class: a positive definite kernel on (n, D) particles.

    Subclasses implement `evaluate` and `pairwise`; `gram` is derived. Kernels
    are immutable and hash by identity (like functions), so they can be static
    arguments of `jax.jit`.
    """

    #: True when the kernel reads features from the log density (see
    #: `feature_kernel`): the log density then returns (logp, features).
    uses_density_features: bool = False

    def evaluate(
        self,
        x: jax.Array,
        weights: jax.Array | None = None,
        *,
        jac: jax.Array | None = None,
        features: tuple[jax.Array, jax.Array] | None = None,
        valid: jax.Array | None = None,
    ) -> KernelTerms:
        """Gram matrix, weighted repulsion and bandwidths at the particles x.

        Args:
          x: (n, D) kernel inputs.
          weights: (n,) weights a_j of the repulsion sum (summing to 1); None for
            uniform 1/n, as in STAMP eq. (1).
          jac: optional (n, D, d) Jacobians of x with respect to θ; the
            repulsion is then returned in θ-space, (n, d).
          features: (F (n, f), J_F (n, f, d)) features from the log density,
            only for a `feature_kernel` without its own feature map.
          valid: (n,) bool or None (all): particles that count. The median
            heuristic and the centring read valid particles only, so an invalid
            one (a non-finite log density, weight 0) changes no other particle's
            terms; its own rows are computed but meaningless.

        Returns:
          KernelTerms(gram (n, n), repulsion (n, D) or (n, d), params).
        """
        raise NotImplementedError

    def pairwise(self, params: Any, x: jax.Array, y: jax.Array) -> jax.Array:
        """k(x, y) for two single points x, y of shape (D,), given bandwidths.

        Slow reference path, for tests and for checking positive definiteness;
        the SVGD steps use `evaluate`.
        """
        raise NotImplementedError

    def gram(self, x: jax.Array) -> jax.Array:
        """The (n, n) Gram matrix at x, bandwidths chosen as in `evaluate`."""
        return self.evaluate(x).gram


@dataclasses.dataclass(frozen=True, eq=False)
class _Stationary(Kernel):
    """exp(−Σ_g ‖e(x)_g − e(y)_g‖² / s_g²) for an elementwise embedding e."""

    groups: tuple[IndexSpec, ...] | None = None
    bandwidth: tuple[Bandwidth, ...] | Bandwidth = "median"

    def __post_init__(self):
        """Validates groups and bandwidths (ValueError naming the bad value)."""
        name = type(self).__name__
        if self.groups is not None:
            if isinstance(self.groups, (slice, str)) or not isinstance(
                self.groups, Sequence
            ):
                raise ValueError(
                    f"{name} groups must be None or a sequence of slices / index "
                    f"sequences; got {self.groups!r}"
                )
            if len(self.groups) == 0:
                raise ValueError(f"{name} groups must hold at least one group")
            for g in self.groups:
                _check_spec(g, f"{name} group")
            object.__setattr__(self, "groups", tuple(self.groups))
        n_groups = 1 if self.groups is None else len(self.groups)
        object.__setattr__(
            self, "bandwidth", _check_bandwidth(self.bandwidth, n_groups)
        )

    # Subclass hooks ---------------------------------------------------------
    def _embed(self, x: jax.Array) -> tuple[jax.Array, int]:
        """(n, D) -> ((n, c*D) embedding laid out as c blocks of D columns, c)."""
        raise NotImplementedError

    def _grad_terms(self, x: jax.Array, lam: jax.Array) -> list:
        """Terms (A, B) of ∇_{x_j} k(x_j, x_i) / k_ji (see `_separable_repulsion`)."""
        raise NotImplementedError

    def _log_pair(self, lam: jax.Array, x: jax.Array, y: jax.Array) -> jax.Array:
        raise NotImplementedError

    # ------------------------------------------------------------------------
    def _group_indices(self, dim: int) -> list[np.ndarray]:
        name = type(self).__name__
        if self.groups is None:
            return [np.arange(dim)]
        idx = [_resolve(g, dim, f"{name} group {k}") for k, g in enumerate(self.groups)]
        _check_cover(idx, dim, f"{name} groups", once=True)
        return idx

    def _bandwidth_specs(self, n_groups: int) -> tuple[Bandwidth, ...]:
        if isinstance(self.bandwidth, tuple):
            return self.bandwidth
        return (self.bandwidth,) * n_groups

    def _lam(self, s: jax.Array, groups: list[np.ndarray], dim: int) -> jax.Array:
        """Per-coordinate 1/s_g², shape (D,)."""
        group_of = np.empty(dim, dtype=int)
        for g, idx in enumerate(groups):
            group_of[idx] = g
        return (1.0 / s**2)[group_of]

    def evaluate(self, x, weights=None, *, jac=None, features=None, valid=None) -> KernelTerms:
        """See `Kernel.evaluate`."""
        if features is not None:
            raise ValueError(
                "features from the log density are read by feature_kernel(...) only; "
                f"got them for a {type(self).__name__} kernel"
            )
        check_particles(x, name="x")
        n, dim = x.shape
        groups = self._group_indices(dim)
        specs = self._bandwidth_specs(len(groups))
        # Distances are translation invariant: centring keeps the expanded
        # ‖a‖² + ‖b‖² − 2a·b accurate in float32.
        x = x - _mean_rows(x, valid)
        z, c = self._embed(x)
        cols = [np.concatenate([idx + k * dim for k in range(c)]) for idx in groups]
        if all(isinstance(b, float) for b in specs):
            s = jnp.asarray(specs, dtype=x.dtype)
            lam = self._lam(s, groups, dim)
            log_k = -_sqdist(z * jnp.sqrt(jnp.tile(lam, c)))
        else:
            s_list, log_k = [], 0.0
            for b, col in zip(specs, cols, strict=True):
                d2 = _sqdist(_take(z, col))
                s_g = (
                    _median_bandwidth_from_sqdist(d2, valid)
                    if b == "median"
                    else jnp.asarray(b)
                )
                s_list.append(s_g.astype(x.dtype))
                log_k = log_k - d2 / s_g**2
            s = jnp.stack(s_list)
            lam = self._lam(s, groups, dim)
        gram = jnp.exp(log_k)
        a = _uniform_weights(n, x.dtype) if weights is None else weights
        repulsion = _separable_repulsion(
            a[:, None] * gram, self._grad_terms(x, lam), jac
        )
        return KernelTerms(gram, repulsion, s)

    def pairwise(self, params, x, y):
        """See `Kernel.pairwise`; params is the (g,) array of bandwidths."""
        dim = x.shape[-1]
        lam = self._lam(jnp.asarray(params), self._group_indices(dim), dim)
        return jnp.exp(self._log_pair(lam, x, y))


@dataclasses.dataclass(frozen=True, eq=False)
class RBF(_Stationary):
    """RBF kernel k(x, y) = exp(−Σ_g ‖x_g − y_g‖² / s_g²), one bandwidth per group.

    Attributes:
      groups: None (one group, all coordinates) or a sequence of slices / index
        sequences that together hold each coordinate exactly once.
      bandwidth: "median" (heuristic, recomputed every step), a float s > 0, or
        one of those per group.

    References:
      STAMP App. B-C (RBF over [θ, w(θ)] with bandwidths s_{v}, s_{w}).
    """

    def _embed(self, x):
        return x, 1

    def _grad_terms(self, x, lam):
        # ∇_{x_j} k_ji = −2 λ ⊙ (x_j − x_i) k_ji.
        return [(-2.0 * lam * x, None), (2.0 * lam, x)]

    def _log_pair(self, lam, x, y):
        return -jnp.sum(lam * (x - y) ** 2)


@dataclasses.dataclass(frozen=True, eq=False)
class VonMises(_Stationary):
    """Von Mises kernel for angles, k(x, y) = exp(Σ_D κ_D (cos(x_D − y_D) − 1)).

    κ_D = 2 / s_g² for the group g of coordinate D. This is the RBF kernel on the
    circle embedding (cos x, sin x), so it is positive definite, periodic with
    period 2π in every coordinate, and its median heuristic uses chord
    distances ‖(cos x, sin x) − (cos y, sin y)‖.

    Attributes:
      groups: as for `RBF`.
      bandwidth: as for `RBF` (in chord-length units, s ≤ 2 is the useful range).

    References:
      STAMP App. C-B (von Mises kernel over the goal angles g_φ).
    """

    def _embed(self, x):
        return jnp.concatenate([jnp.cos(x), jnp.sin(x)], axis=1), 2

    def _grad_terms(self, x, lam):
        # ∇_{x_j} k_ji = −2λ sin(x_j − x_i) k_ji, sin(a−b) = sin a cos b − cos a sin b.
        return [
            (-2.0 * lam * jnp.sin(x), jnp.cos(x)),
            (2.0 * lam * jnp.cos(x), jnp.sin(x)),
        ]

    def _log_pair(self, lam, x, y):
        return jnp.sum(2.0 * lam * (jnp.cos(x - y) - 1.0))


@dataclasses.dataclass(frozen=True, eq=False)
class SumKernel(Kernel):
    """k(x, y) = Σ_t α_t k_t(x[I_t], y[I_t]): a weighted sum over parts of x.

    A sum of positive definite kernels with positive weights is positive
    definite. The index sets I_t may overlap but must together cover every
    coordinate, so that every coordinate feels the repulsion.

    Attributes:
      terms: tuple of (weight α_t > 0, kernel k_t, index set I_t), I_t a slice
        or a sequence of ints.

    References:
      STAMP App. C-B (weighted sum of RBF and von Mises kernels).
    """

    terms: tuple[tuple[float, Kernel, IndexSpec], ...] = ()

    def __post_init__(self):
        """Validates the terms (ValueError naming the bad term)."""
        if len(self.terms) == 0:
            raise ValueError(
                "sum_kernels needs at least one (weight, kernel, index) term"
            )
        clean = []
        for t, term in enumerate(self.terms):
            try:
                weight, kernel, spec = term
            except (TypeError, ValueError):
                raise ValueError(
                    f"sum_kernels term {t} must be (weight, kernel, index); "
                    f"got {term!r}"
                ) from None
            if not (float(weight) > 0 and math.isfinite(float(weight))):
                raise ValueError(
                    f"sum_kernels term {t} weight must be > 0; got {weight!r}"
                )
            if not isinstance(kernel, Kernel):
                raise ValueError(
                    f"sum_kernels term {t} kernel must be a Kernel; got {kernel!r}"
                )
            if kernel.uses_density_features:
                raise ValueError(
                    f"sum_kernels term {t}: a feature_kernel without feature_fn reads "
                    "the log density's features and must be the outermost kernel"
                )
            _check_spec(spec, f"sum_kernels term {t} index")
            clean.append((float(weight), kernel, spec))
        object.__setattr__(self, "terms", tuple(clean))

    def _indices(self, dim: int) -> list[np.ndarray]:
        idx = [
            _resolve(s, dim, f"sum_kernels term {t} index")
            for t, (_, _, s) in enumerate(self.terms)
        ]
        _check_cover(idx, dim, "sum_kernels terms", once=False)
        return idx

    def evaluate(self, x, weights=None, *, jac=None, features=None, valid=None) -> KernelTerms:
        """See `Kernel.evaluate`."""
        if features is not None:
            raise ValueError(
                "features from the log density are read by an outermost "
                "feature_kernel(...) only; got them for sum_kernels"
            )
        check_particles(x, name="x")
        n, dim = x.shape
        gram = jnp.zeros((n, n), x.dtype)
        repulsion = jnp.zeros((n, dim if jac is None else jac.shape[-1]), x.dtype)
        params = []
        for (w, kernel, _), idx in zip(self.terms, self._indices(dim), strict=True):
            sub_jac = None if jac is None else jac[:, idx, :]
            ev = kernel.evaluate(_take(x, idx), weights, jac=sub_jac, valid=valid)
            gram = gram + w * ev.gram
            if jac is None:
                repulsion = repulsion.at[:, idx].add(w * ev.repulsion)
            else:
                repulsion = repulsion + w * ev.repulsion
            params.append(ev.params)
        return KernelTerms(gram, repulsion, tuple(params))

    def pairwise(self, params, x, y):
        """See `Kernel.pairwise`; params holds one entry per term."""
        total = 0.0
        for (w, kernel, _), idx, p in zip(
            self.terms, self._indices(x.shape[-1]), params, strict=True
        ):
            total = total + w * kernel.pairwise(p, x[idx], y[idx])
        return total


@dataclasses.dataclass(frozen=True, eq=False)
class FeatureKernel(Kernel):
    """k(θ, θ') = k₀(ψ(θ), ψ(θ')) with ψ(θ) = [θ, φ(θ)] (or φ(θ) alone).

    The repulsion ∇_θ k goes through φ by the chain rule, with the per-particle
    Jacobians ∂φ/∂θ computed in one batched pass.

    Attributes:
      base: the kernel k₀ on ψ-space. None: an RBF with a median bandwidth per
        block, [θ] and [φ(θ)] (App. B-C), or one block when include_inputs is
        False.
      feature_fn: batched, particle-separable map (n, d) -> (n, f). None: the
        features come from the log density, which then returns
        (logp (n,), features (n, f)) from the same batched call (one rollout
        gives both); this kernel must then be the outermost one.
      include_inputs: ψ = [θ, φ(θ)] when True, ψ = φ(θ) when False.
      jacobian: how to get ∂φ/∂θ for feature_fn: 'auto', 'fwd' or 'rev'.

    References:
      STAMP App. B-C (kernel over [v, w_{1:4}(v)]; the repulsion needs ∂w/∂v),
      App. C-B (RBF over softmax(s)).
    """

    base: Kernel | None = None
    feature_fn: Callable[[jax.Array], jax.Array] | None = None
    include_inputs: bool = True
    jacobian: JacobianMode = "auto"

    def __post_init__(self):
        """Validates base, feature_fn and jacobian."""
        if self.base is not None and not isinstance(self.base, Kernel):
            raise ValueError(
                f"feature_kernel base must be a Kernel or None; got {self.base!r}"
            )
        if self.feature_fn is not None and not callable(self.feature_fn):
            raise ValueError(
                f"feature_fn must be callable or None; got {self.feature_fn!r}"
            )
        check_mode(self.jacobian, "feature_kernel jacobian")

    @property
    def uses_density_features(self) -> bool:  # type: ignore[override]
        """True when feature_fn is None: the log density supplies the features."""
        return self.feature_fn is None

    def _base(self, d: int, f: int) -> Kernel:
        if self.base is not None:
            return self.base
        if self.include_inputs:
            return RBF(groups=(slice(0, d), slice(d, d + f)))
        return RBF()

    def _embed(self, x, features):
        n, d = x.shape
        if self.feature_fn is not None:
            if features is not None:
                raise ValueError(
                    "feature_kernel has its own feature_fn; got density features too"
                )
            feats, feats_jac = value_and_batched_jacobian(
                self.feature_fn, x, self.jacobian
            )
        elif features is None:
            raise ValueError(
                "feature_kernel(feature_fn=None) reads its features from the log "
                "density: logdensity_fn must return (logp (n,), features (n, f)), "
                "and this kernel must be the outermost one"
            )
        else:
            feats, feats_jac = features
        if (
            feats.ndim != 2
            or feats.shape[0] != n
            or feats_jac.shape != (*feats.shape, d)
        ):
            raise ValueError(
                f"features must have shape (n, f) = ({n}, f) with Jacobians (n, f, d); "
                f"got {feats.shape} and {feats_jac.shape}"
            )
        if not self.include_inputs:
            return feats, feats_jac
        eye = jnp.broadcast_to(jnp.eye(d, dtype=x.dtype), (n, d, d))
        psi = jnp.concatenate([x, feats.astype(x.dtype)], axis=1)
        return psi, jnp.concatenate([eye, feats_jac.astype(x.dtype)], axis=1)

    def evaluate(self, x, weights=None, *, jac=None, features=None, valid=None) -> KernelTerms:
        """See `Kernel.evaluate`; the repulsion is returned in θ-space, (n, d)."""
        check_particles(x, name="x")
        psi, psi_jac = self._embed(x, features)
        if jac is not None:
            psi_jac = jnp.einsum("nek,nkd->ned", psi_jac, jac)
        base = self._base(x.shape[1], psi.shape[1] - x.shape[1] * self.include_inputs)
        return base.evaluate(psi, weights, jac=psi_jac, valid=valid)

    def embed(self, x: jax.Array) -> jax.Array:
        """ψ(x) for one point x of shape (d,); needs feature_fn."""
        if self.feature_fn is None:
            raise ValueError(
                "feature_kernel(feature_fn=None) has no feature map of its own; "
                "pass feature_fn to evaluate it pointwise"
            )
        feats = self.feature_fn(x[None])[0]
        return jnp.concatenate([x, feats]) if self.include_inputs else feats

    def pairwise(self, params, x, y):
        """See `Kernel.pairwise`; needs feature_fn."""
        ex, ey = self.embed(x), self.embed(y)
        f = ex.shape[0] - x.shape[0] * self.include_inputs
        return self._base(x.shape[0], f).pairwise(params, ex, ey)


# ----------------------------------------------------------------------------
# Constructors (the public, functional spelling)


def rbf(groups: Sequence[IndexSpec] | None = None, bandwidth: Any = "median") -> RBF:
    """RBF kernel with one bandwidth per group of coordinates.

    Args:
      groups: None for a single group, or slices / index sequences that hold
        each coordinate exactly once, e.g. `(slice(0, 2), slice(2, None))`.
      bandwidth: "median", a float s > 0 (k = exp(−‖Δ‖²/s²); blackjax's
        `length_scale` is s²), or one of those per group.

    Returns:
      An `RBF` kernel.

    References:
      STAMP App. B-C.
    """
    return RBF(groups=None if groups is None else tuple(groups), bandwidth=bandwidth)


def von_mises(
    groups: Sequence[IndexSpec] | None = None, bandwidth: Any = "median"
) -> VonMises:
    """Von Mises kernel for angles (wrap-around), one bandwidth per group.

    Args:
      groups: as for `rbf`.
      bandwidth: as for `rbf`; the concentration is κ = 2 / s².

    Returns:
      A `VonMises` kernel.

    References:
      STAMP App. C-B.
    """
    return VonMises(
        groups=None if groups is None else tuple(groups), bandwidth=bandwidth
    )


def sum_kernels(terms: Sequence[tuple[float, Kernel, IndexSpec]]) -> SumKernel:
    """Weighted sum of kernels over parts of θ, Σ_t α_t k_t(θ[I_t], θ'[I_t]).

    Args:
      terms: (weight α_t > 0, kernel, index set I_t) triples whose index sets
        together cover every coordinate of θ.

    Returns:
      A `SumKernel`.

    References:
      STAMP App. C-B.
    """
    return SumKernel(terms=tuple(terms))


def feature_kernel(
    base: Kernel | None = None,
    feature_fn: Callable[[jax.Array], jax.Array] | None = None,
    *,
    include_inputs: bool = True,
    jacobian: JacobianMode = "auto",
) -> FeatureKernel:
    """Kernel over a differentiable feature map, k₀([θ, φ(θ)], [θ', φ(θ')]).

    Args:
      base: kernel k₀ on [θ, φ(θ)]; None for an RBF with a median bandwidth per
        block [θ], [φ(θ)] (App. B-C).
      feature_fn: batched (n, d) -> (n, f) feature map, or None to read the
        features the log density returns alongside log ρ (one batched rollout
        gives both; see `build_svgd_step`).
      include_inputs: False to use φ(θ) alone.
      jacobian: 'auto', 'fwd' or 'rev' for ∂φ/∂θ when feature_fn is given.

    Returns:
      A `FeatureKernel`.

    References:
      STAMP App. B-C.
    """
    return FeatureKernel(
        base=base,
        feature_fn=feature_fn,
        include_inputs=include_inputs,
        jacobian=jacobian,
    )


def median_bandwidth(
    x: jax.Array, groups: Sequence[IndexSpec] | None = None
) -> jax.Array:
    """Median-heuristic RBF bandwidths, s_g = median_{i<j} ‖x_ig − x_jg‖ / √(log n).

    Args:
      x: (n, D) particles, n >= 2.
      groups: as for `rbf`.

    Returns:
      (g,) bandwidths, one per group (1.0 for a group whose median distance is 0).

    References:
      STAMP App. B-C; Liu & Wang (2016), SVGD.
    """
    x = jnp.asarray(x)
    check_particles(x, name="x")
    groups = tuple(
        tuple(idx.tolist()) for idx in rbf(groups)._group_indices(x.shape[1])
    )
    return _median_bandwidths(x, groups)


@functools.partial(jax.jit, static_argnums=1)
def _median_bandwidths(x: jax.Array, groups: tuple[tuple[int, ...], ...]) -> jax.Array:
    x = x - jnp.mean(x, axis=0)
    return jnp.stack(
        [
            _median_bandwidth_from_sqdist(_sqdist(_take(x, np.asarray(g))))
            for g in groups
        ]
    )
