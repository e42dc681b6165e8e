"""mjstamp.svgd: the Stein engine (kernels, SVGD / discrete SVGD / SGD, STAMP loop).

What it is for: inference over particles on any differentiable, batched log
density, in the manner of blackjax and optax (a state NamedTuple, `build_*`
factories returning `step(state, key) -> (state, info)`, optax for updates).

What it may import: the standard library, jax, numpy, optax, tqdm, its own
modules, `mjstamp.progress` (the one progress reporter, itself the standard library
alone) and `mjstamp.errors` (a leaf that imports nothing: bad settings raise the
`MjstampError` the rest of mjstamp raises). Never `mujoco` nor `mjstamp.relax`
(nor the rest of mjstamp): the engine
knows nothing of physics or task plans, and toy densities such as Figure 1's live
in `benchmarks/paper/mixture.py` (tests/test_svgd_imports.py checks this).

A task plugs in one batched, particle-separable function (row i of every output
depends on particle i only), called once per step on the whole batch:

    def log_posterior(theta):                # theta: (n, d)
        traj = rollout(theta)                # the vmapped simulation, n rollouts
        w = relax.soft_contact_indicator(...)  # (n, f) features of the same rollout
        return -cost(traj, w), w             # ((n,), (n, f))

    result = svgd.run_stamp(
        log_posterior, theta0, svgd.feature_kernel(), svgd.StampConfig()
    )

`feature_kernel()` (no feature_fn) takes w from the log density and puts an RBF
with a median bandwidth per block over [θ, w(θ)] (App. B-C); log ρ, w and all
their per-particle Jacobians come from that one batched call. Without features,
return (log ρ, an (n, 0) array) and use any kernel (default `rbf()`): one
signature, `logdensity(θ) -> (logp, aux)`, as `jax.value_and_grad(has_aux=True)`
reads it. See
`mjstamp.svgd.steps` for the contract, `run_stamp` for the loop and
`mjstamp.svgd.guards` for the pure guards around its steps (backtracking, re-draws).

References:
  STAMP §III-A, §IV-A/B, Algorithm 1, App. B-C, App. C-B.
"""

from mjstamp.svgd.config import StampConfig
from mjstamp.svgd.diagnostics import StampDiagnostics, StampResult, has_converged
from mjstamp.svgd.guards import PHASE_SGD, PHASE_SVGD
from mjstamp.svgd.kernels import (
    RBF,
    FeatureKernel,
    Kernel,
    KernelTerms,
    SumKernel,
    VonMises,
    feature_kernel,
    flat_bandwidths,
    median_bandwidth,
    rbf,
    sum_kernels,
    von_mises,
)
from mjstamp.svgd.polish import (
    PolishConfig,
    PolishResult,
    PolishState,
    build_polish_step,
    run_polish,
)
from mjstamp.svgd.resume import LoopSnapshot
from mjstamp.svgd.stamp import run_stamp
from mjstamp.svgd.steps import (
    NEAR_ZERO_ATOL,
    NEAR_ZERO_RTOL,
    Evaluation,
    StepInfo,
    SVGDState,
    build_dsvgd_step,
    build_evaluate,
    build_sgd_step,
    build_svgd_step,
    importance_log_weights,
    init,
    near_zero_share,
    near_zero_threshold,
    stein_direction,
)

__all__ = [
    "NEAR_ZERO_ATOL",
    "NEAR_ZERO_RTOL",
    "PHASE_SGD",
    "PHASE_SVGD",
    "LoopSnapshot",
    "PolishConfig",
    "PolishResult",
    "PolishState",
    "StampConfig",
    "StampDiagnostics",
    "StampResult",
    "has_converged",
    "run_stamp",
    "FeatureKernel",
    "Kernel",
    "KernelTerms",
    "RBF",
    "Evaluation",
    "SVGDState",
    "StepInfo",
    "SumKernel",
    "VonMises",
    "build_dsvgd_step",
    "build_evaluate",
    "build_polish_step",
    "build_sgd_step",
    "build_svgd_step",
    "feature_kernel",
    "flat_bandwidths",
    "importance_log_weights",
    "init",
    "median_bandwidth",
    "near_zero_share",
    "near_zero_threshold",
    "rbf",
    "run_polish",
    "stein_direction",
    "sum_kernels",
    "von_mises",
]
