"""rsmooth: randomized smoothing for optimizing non-smooth physical processes in JAX."""
