"""sync4d: video-guided, physics-based motion transfer onto 3D Gaussians (Sync4D, Fu et al. 2024)."""

__version__ = "0.1.0"
