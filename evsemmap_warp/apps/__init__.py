"""Applications: the command line (``cli``), batch mapping (``batch``), experiments and their scores
(``experiment``, ``evaluation``), scan sources for them (``scan_sources``) and the browser viewer
(``viewer``)."""
