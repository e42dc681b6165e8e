"""mjstamp's version: a leaf, so the modules that stamp it on files skip the package face."""

__version__ = "0.1.0"
