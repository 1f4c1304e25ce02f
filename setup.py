"""Package discovery (everything else is in pyproject.toml): every package under evsemmap_warp/,
found automatically, plus the two top-level folders that install as its subpackages."""

from setuptools import find_packages, setup

setup(packages=find_packages(include=["evsemmap_warp", "evsemmap_warp.*"]) + ["evsemmap_warp.kernels", "evsemmap_warp.configs"])
