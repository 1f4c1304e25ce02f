"""Warp kernels of evsemmap_warp (importable as ``evsemmap_warp.kernels``).

Kernels take arrays and return arrays; configs, files and control flow live in the Python layer.
Every kernel module here has a plain numpy twin in ``evsemmap_warp/reference/`` with the same
function names, and the tests hold the two against each other. Importing this package compiles
nothing: Warp builds a module on its first launch.
"""
