"""mjstamp.svgd: the Stein engine (kernels, SVGD / discrete SVGD / SGD, STAMP loop).

Pure JAX on any differentiable, batched log density: nothing here imports MuJoCo.
A task plugs in `logdensity_fn(particles (n, d)) -> (n,)`, or
`-> (logp (n,), features (n, f))` with `feature_kernel()`; see
`mjstamp.svgd.steps` for the contract and `run_stamp` for the full loop.

References:
  STAMP §III-A, §IV-A/B, Algorithm 1, App. B-C, App. C-B.
"""

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
from mjstamp.svgd.stamp import (
    PHASE_SGD,
    PHASE_SVGD,
    StampConfig,
    StampDiagnostics,
    StampResult,
    has_converged,
    run_stamp,
)
from mjstamp.svgd.steps import (
    StepInfo,
    SVGDState,
    build_dsvgd_step,
    build_sgd_step,
    build_svgd_step,
    importance_log_weights,
    init,
    stein_direction,
)

__all__ = [
    "PHASE_SGD",
    "PHASE_SVGD",
    "StampConfig",
    "StampDiagnostics",
    "StampResult",
    "has_converged",
    "run_stamp",
    "FeatureKernel",
    "Kernel",
    "KernelTerms",
    "RBF",
    "SVGDState",
    "StepInfo",
    "SumKernel",
    "VonMises",
    "build_dsvgd_step",
    "build_sgd_step",
    "build_svgd_step",
    "feature_kernel",
    "flat_bandwidths",
    "importance_log_weights",
    "init",
    "median_bandwidth",
    "rbf",
    "stein_direction",
    "sum_kernels",
    "von_mises",
]
