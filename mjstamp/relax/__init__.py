"""mjstamp.relax: pure functions of arrays that relax discrete plan variables.

What it is for: Γ / Γ̃ (hard and soft one-hots per block), the uniform base
distribution p₀, soft contact indicators and softmin aggregations.

What it may import: jax and numpy only (no MuJoCo, no `mjstamp.svgd`).

References:
  STAMP §IV-A, App. A, App. B-B, App. B-D.
"""

from mjstamp.relax.contact import (
    first_contact_mask,
    soft_contact_indicator,
    softmin_aggregate,
)
from mjstamp.relax.onehot import (
    block_labels,
    hard_onehot,
    soft_onehot,
    uniform_base_sample,
)

__all__ = [
    "block_labels",
    "first_contact_mask",
    "hard_onehot",
    "soft_contact_indicator",
    "soft_onehot",
    "softmin_aggregate",
    "uniform_base_sample",
]
