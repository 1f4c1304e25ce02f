"""The synthetic off-road world: a procedural scene (``scene``), its look (``appearance``), Warp
ray-cast sensors (``sensors``) and a writer of RELLIS-3D-layout sequences (``writer``)."""
