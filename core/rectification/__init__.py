"""Rectification: the adaptive lattice of exact raw coordinates (:mod:`.lattice`), the
compiled pixel kernels (:mod:`.kernel`) and multi-band raw-image reading
(:mod:`.rawimage`)."""
