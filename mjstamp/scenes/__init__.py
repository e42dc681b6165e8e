"""mjstamp.scenes."""
