"""evsemmap_warp: evidential semantic mapping (uncertainty-aware BKI) on Warp kernels.

Importing the package initialises Warp but compiles nothing; kernels build on their first launch.
"""

__version__ = "0.1.0"

from .config import Compat, ConfigError, Kernel, MappingConfig, Media, PayloadType, load_config  # noqa: E402
from .core.map_file import MapFileError  # noqa: E402
from .core.mapper import UNKNOWN_LABEL, Mapper, QueryResult, VoxelState, load_map, save_map  # noqa: E402
from .data.pcd import PcdError, read_pcd  # noqa: E402

__all__ = [
    "Compat", "ConfigError", "Kernel", "MapFileError", "Mapper", "MappingConfig", "Media", "PayloadType",
    "PcdError", "QueryResult", "UNKNOWN_LABEL", "VoxelState", "load_config", "load_map", "read_pcd", "save_map",
]
