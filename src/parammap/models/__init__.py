"""Appearance models fitted per texel: Multiple Highlight (mh) and spherical harmonics (sh)."""
