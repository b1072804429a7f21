"""Evaluation, reporting and benchmark tools around the sync4d library (which never imports them)."""
