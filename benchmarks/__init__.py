"""Benchmarks, grouped by kind: `paper/`, `perf/`, `studies/` (see benchmarks/README.md).

Not part of the installed package. A package so that each script runs as
`python -m benchmarks.KIND.NAME` from the repository root (or by its path), and
so that tests can import Figure 1's toy (`from benchmarks.paper.mixture import
...`, with the repository root on sys.path). `common.py` holds what the scripts
repeat; nothing in `mjstamp` imports them.
"""
