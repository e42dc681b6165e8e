"""Moved to `mjstamp.distance` (signed distances of geom pairs); works for one release."""

from mjstamp._moved import alias

alias(__name__, "mjstamp.distance")
