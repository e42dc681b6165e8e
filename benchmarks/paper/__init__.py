"""Reproductions of the paper: Figure 1 (with its toy, mixture.py), Tables I-III, Fig. 7's modes."""
