"""Geometry: pinhole cameras (``camera``), projection of images onto LiDAR points (``projection``)
and TF trees (``transform_tree``)."""
