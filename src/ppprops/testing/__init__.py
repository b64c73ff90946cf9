"""Test and soak helpers that ship with the package (so `benchmarks/soak.py` and CI can use them).

Nothing here is imported by a normal run.
"""
