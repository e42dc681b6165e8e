"""mjstamp.relax."""
