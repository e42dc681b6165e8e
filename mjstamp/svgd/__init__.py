"""mjstamp.svgd."""
