"""Every Warp kernel has a numpy twin of the same name (style recommendation 1)."""

import importlib
import pkgutil

import warp as wp

import evsemmap_warp.kernels as kernels_pkg

# Modules of Warp functions that the kernels share, without kernels of their own to twin.
FUNCTION_MODULES = {"indexing"}


def test_every_kernel_module_and_kernel_has_a_numpy_twin():
    modules = [m.name for m in pkgutil.iter_modules(kernels_pkg.__path__)]
    assert modules, "no kernel modules found"
    for name in sorted(set(modules) - FUNCTION_MODULES):
        kernel_module = importlib.import_module(f"evsemmap_warp.kernels.{name}")
        twin = importlib.import_module(f"evsemmap_warp.reference.{name}")
        kernels = [n for n, obj in vars(kernel_module).items() if isinstance(obj, wp.Kernel) and obj.module.name == kernel_module.__name__]
        kernels += list(getattr(kernel_module, "KERNEL_FACTORIES", {}))  # kernels made per parameter (e.g. per class count)
        assert kernels, f"{name} defines no kernels"
        missing = [k for k in kernels if not callable(getattr(twin, k, None))]
        assert not missing, f"evsemmap_warp/reference/{name}.py lacks twins for {missing}"


def test_the_function_modules_define_no_kernels():
    for name in FUNCTION_MODULES:
        module = importlib.import_module(f"evsemmap_warp.kernels.{name}")
        assert not [n for n, obj in vars(module).items() if isinstance(obj, wp.Kernel)], f"kernels/{name}.py defines kernels: give it a twin"
