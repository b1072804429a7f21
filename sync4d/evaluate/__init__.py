"""``python -m sync4d.evaluate <name>``: a thin entry point to :mod:`sync4d_tools.evaluate`.

The evaluation commands live outside the library (they import it, never the other way round).
"""
