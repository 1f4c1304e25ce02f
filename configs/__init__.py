"""The built-in configs, installed as ``evsemmap_warp.configs``: methods, mapping presets, dataset
configs, class sets, synthetic presets, experiments and terrain cost tables (YAML files)."""
