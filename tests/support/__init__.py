"""Code the tests share that is no part of the package: structure-aware hostile episodes (mutate.py)."""
