"""Warp kernels of evsemmap_warp (importable as ``evsemmap_warp.kernels``).

Kernels take arrays and return arrays; configs, files and control flow live in the Python layer.
Every kernel module here has a plain numpy twin in ``evsemmap_warp/reference/`` with the same
function names, and the tests hold the two against each other. Importing this package compiles
nothing: Warp builds a module on its first launch.
"""

import threading

# The options every kernel module here is built with (``wp.set_module_options`` in each module, and the
# ``module_options`` of the kernels factories build as modules of their own). fuse_fp off: a CUDA build
# otherwise contracts a * b + c into one fused multiply-add, which a CPU build does not, and the device
# paths and the compatibility modes promise the CPU's results bit for bit on any device.
MODULE_OPTIONS = {"enable_backward": False, "fuse_fp": False}

# (device, id of the module) -> the module, kept so that its id is never reused.
_loaded: dict = {}
_loading = threading.Lock()


def load_once(module, device: str) -> None:
    """Compile, or load from the kernel cache, a module of kernels (a Python module of this package, or
    the Warp module of a kernel a factory made) for ``device``, once per process and under one lock: the
    thread that first launches a module's kernels never races another one loading it, and a command
    compiles only the modules it launches (a clean-mode map needs two of them, a map file's queries one)."""
    key = (device, id(module))
    if key in _loaded:
        return
    with _loading:
        if key not in _loaded:
            import warp as wp

            # wp.load_module builds the variant a launch uses (on the CPU, blocks of one thread); a Warp
            # module's own load() builds its default block size of 256, which no CPU launch runs: the
            # launch then compiled the module a second time.
            wp.load_module(module, device=device)
            _loaded[key] = module
