"""GCGS: sparse-view surface reconstruction with geometric-consistent 2D Gaussian surfels."""

__version__ = "0.1.0"
