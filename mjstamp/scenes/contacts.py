"""Moved to `mjstamp.colliders` (C's colliders ported to JAX); works for one release."""

from mjstamp._moved import alias

alias(__name__, "mjstamp.colliders", submodules=(
    "box_box", "capsule_box", "cmath", "compare", "convex", "gjk", "gjk_multi", "primitive"))
