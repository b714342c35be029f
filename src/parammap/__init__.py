"""parammap: from bracketed photos of a flat surface to per-texel parameter maps."""

__version__ = "0.1.0"
