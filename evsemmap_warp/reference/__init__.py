"""Slow, readable numpy twins of the Warp kernels in ``evsemmap_warp.kernels``.

One file per kernel module, same function names, float64 accumulation, no code shared with the
kernels. Tests hold every kernel against its twin on random inputs and edge cases.
"""
