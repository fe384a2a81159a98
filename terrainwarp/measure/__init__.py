"""Measuring frames: the primary screen-space error at the heightmap's samples and popping
(:mod:`.sample_error`), the per-pixel image error against the fixed-diagonal grid (:mod:`.error`, a secondary
measure with a triangulation floor), and image metrics."""
