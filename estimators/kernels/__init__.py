"""Compiled per-sample loops (numba, ``cache=True``) shared by the estimators."""
