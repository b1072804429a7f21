"""Run loggers (group ``logger``): TensorBoard event files (scalars, images, the compare clip as an animated
GIF, hyper-parameters) or nothing."""
