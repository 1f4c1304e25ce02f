"""Evidential semantic segmentation (docs/algorithm.md §1): DeepLabV3 in plain PyTorch, the EDL head and
loss, image datasets, training, inference and 2D metrics."""
