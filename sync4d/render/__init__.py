"""sync4d.render: Gaussian splatting renderers (``render=splat_torch``, ``render=gsplat``), SH colours,
cameras (look-at, framing, turntable) and videos (mp4/GIF, side-by-side comparison, TensorBoard GIFs)."""
