"""Per-point shape descriptors for part matching (group ``features``): ``geometric`` (heat and wave kernel
signatures plus coordinates, no weights), ``diff3f`` (multi-view 2D features back-projected to the vertices:
a download-free stand-in, or DINOv2 / Stable Diffusion from local weights) and ``concat`` (several of them,
weighted)."""
