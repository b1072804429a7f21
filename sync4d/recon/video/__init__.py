"""``recon=video`` as a package of typed stages (see :mod:`sync4d.recon.video.reconstructor`)."""

from sync4d.recon.video.images import (
    background_masks, flow_consistency, optical_flow, rotation_angle_deg, sample_image, track_points, trusted_tracks,
)
from sync4d.recon.video.reconstructor import VideoFit, VideoReconstructor

__all__ = ["VideoFit", "VideoReconstructor", "background_masks", "flow_consistency", "optical_flow",
           "rotation_angle_deg", "sample_image", "track_points", "trusted_tracks"]
