"""Truths that the transfer never sees: the target's own skinning model, and an elastic solid (libigl ARAP)."""
