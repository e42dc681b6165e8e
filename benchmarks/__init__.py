"""Benchmark scripts (each runs as `python benchmarks/NAME.py`) and the toy problems they share.

Not part of the installed package. A package only so that tests can import the
shared toys (`from benchmarks.mixture import ...`, with the repository root on
sys.path); the scripts may import `mjstamp` and each other, nothing imports them.
"""
