"""Labelled targets of the cross-category matching benchmark (``python -m sync4d.evaluate match_gt --cross-category``).

Each ``*.json`` file here is one target with its limb labels and the reference parts each label should
receive; :mod:`sync4d_tools.match_labels.labels` reads them (format documented there and in
docs/results/matching.md); :mod:`sync4d_tools.match_labels.procedural` builds the procedural chair, table and lamp.
"""
