"""Whole movies: the run plan, the frame cache, the reference, the shared-motion pass, blocks
of target frames with their carried guesses and trust checks, the refined reference, sinks,
the runner and the distributed runner.

Layer 4: imports from every layer below (kernels, core, io, analysis)."""
