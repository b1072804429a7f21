"""Reconstruction (group ``recon``): an articulated reference (rest mesh, Gaussian bones, skinning, per-frame
bone transforms) from what a reference source gives: a video (``video``, ``body_video``; ``video/`` and
``pose/``), motion capture (``mocap``), a posed mesh sequence (``skinning_fit``), a Lab4D export (``lab4d``),
or the exact bones a synthetic source carries (``ground_truth``)."""
