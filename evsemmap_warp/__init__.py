"""evsemmap_warp: evidential semantic mapping (uncertainty-aware BKI) on Warp kernels.

The public API is what this module exports (``__all__``, listed in docs/reference/index.md), with the
``evsemmap`` command line, the config files and the file formats: these change only through a
deprecation release, the old name kept for one release with a warning. The subpackages in ``__all__``
(``terrain``) are public with their own ``__all__``. Every other module is internal: importable, and
documented for contributors, but free to change; a leading underscore marks a module as private to its
package.

Importing the package loads nothing heavy: each public name imports its module (and Warp, for those that
launch kernels) on first use, so that ``evsemmap`` can answer Ctrl-C in one line from its first moment.
Kernels build on their first launch.
"""

__version__ = "0.1.0"

# Public names -> the module that holds them, imported on first use (None: the subpackage itself).
_LAZY = {
    **dict.fromkeys(("Compat", "ConfigError", "Fusion", "Kernel", "MappingConfig", "Media", "PayloadType", "available_methods",
                     "load_config", "preset_path"), "config"),
    "MapFileError": "core.map_file",
    **dict.fromkeys(("UNKNOWN_LABEL", "Mapper", "MapVoxels", "QueryResult", "VoxelState", "load_map", "save_map"), "core.mapper"),
    "PcdError": "data.pcd", "read_pcd": "data.pcd",
    "MapStore": "core.map_store", "StoreError": "core.map_store", "open_dataset": "data.datasets", "terrain": None,
}

__all__ = [
    "Compat", "ConfigError", "Fusion", "Kernel", "MapFileError", "MapStore", "MapVoxels", "Mapper", "MappingConfig", "Media",
    "PayloadType", "PcdError", "QueryResult", "StoreError", "UNKNOWN_LABEL", "VoxelState", "available_methods", "load_config",
    "load_map", "open_dataset", "preset_path", "read_pcd", "save_map", "terrain",
]


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'evsemmap_warp' has no attribute {name!r}")
    import importlib

    module = importlib.import_module(f".{_LAZY[name] or name}", __name__)
    return module if _LAZY[name] is None else getattr(module, name)


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
