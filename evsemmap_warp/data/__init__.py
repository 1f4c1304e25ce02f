"""Data in: sequence folders (``sequences``), datasets for the mapper (``datasets``), point files
(``point_files``, ``pcd``), robot logs (``logs``, ``ros_messages``, ``log_writer``) and where their
scans are placed in the world (``world_frame``)."""
