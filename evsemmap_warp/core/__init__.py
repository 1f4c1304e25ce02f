"""The map core: the ``Mapper`` (``mapper``), its integrators (``integrators``), the voxel map on a Warp
device (``voxel_map``), map files (``map_file``) and map stores (``map_store``)."""
