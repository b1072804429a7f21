"""Reference sources: what a reconstructor is given (files, videos with their front end, mocap, exports)."""
