"""Measuring frames: screen-space error and image metrics."""
