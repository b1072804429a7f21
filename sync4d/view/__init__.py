"""A local web viewer of finished runs: ``python -m sync4d.view <run folder> [<run folder> ...] [--port P]``.

Built on viser (its wheel ships the built web client, and it renders Gaussian splats): play, pause and
scrub a run's 4D Gaussians beside its input video frame and its reconstructed reference, toggle part
colours, matched part boxes and the simulation particles, and show several runs (e.g. a sweep's
methods) as rows. See docs/guide/viewer.md.
"""
