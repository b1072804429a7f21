"""The run: one typed plan, the stages wired in order, what a run writes."""
