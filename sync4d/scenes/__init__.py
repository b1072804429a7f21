"""Procedural scenes made in code, no files needed: the laptop (reference and target, with its own exact bones,
filmed by :mod:`~sync4d.scenes.reference_video` when a reconstructor wants a video), the clam shell and the
cross targets. The default run (``reference=laptop target=shell``) and most tests use them."""
