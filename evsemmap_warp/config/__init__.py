"""Configs are data: small dataclasses resolved from YAML files in one place (``load_config``).

A run combines a *method* file (``configs/methods/NAME.yaml``: which kernel, which media, which
uncertainty switches) with any number of preset and dataset files (numbers and data sources). Files
are merged in order, later files winning key by key; unknown keys and inconsistent values raise.

The package's modules: ``enums`` (the values of the enumerated keys), ``mapping`` (the ``mapping``
section and its mode sections), ``dataset`` (the ``dataset`` section and a log's ``dataset.bag``),
``convert`` (YAML into a dataclass, each key checked) and ``loading`` (``load_config`` and the files,
presets and inputs it finds). Every name below is imported from here.
"""

from .convert import convert_value, dataclass_from_dict, read_yaml_file
from .dataset import BagConfig, DatasetConfig
from .enums import Compat, Fusion, Kernel, Media, PayloadType, ScatterStrategy, ThresholdScope
from .errors import ConfigError
from .loading import (LOG_SUFFIXES, METHOD_KEYS, RunConfig, available_methods, dataset_for_folder, is_robot_log, load_config,
                      method_path, methods_dir, preset_path)
from .mapping import (MAPPING_SECTIONS, MAX_VOXELS_PER_POINT, CleanSettings, ConvBkiSettings, MappingConfig, ReleaseSettings,
                      SbkiSettings, flat_items)

__all__ = [
    "BagConfig", "CleanSettings", "Compat", "ConfigError", "ConvBkiSettings", "DatasetConfig", "Fusion", "Kernel", "LOG_SUFFIXES",
    "MAPPING_SECTIONS", "MAX_VOXELS_PER_POINT", "METHOD_KEYS", "MappingConfig", "Media", "PayloadType", "ReleaseSettings", "RunConfig",
    "SbkiSettings", "ScatterStrategy", "ThresholdScope", "available_methods", "convert_value", "dataclass_from_dict", "dataset_for_folder",
    "is_robot_log", "load_config", "method_path", "methods_dir", "preset_path", "read_yaml_file", "flat_items",
]
