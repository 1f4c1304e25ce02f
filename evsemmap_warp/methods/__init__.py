"""The comparison methods' and compatibility modes' per-scan rules: the original S-BKI / S-CSM
(``sbki_compat``), the released EvSemMap (the release mode, ``release_compat``), ConvBKI (``convbki``)
and SEE-CSOM (``see_csom``)."""
