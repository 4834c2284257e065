"""Test-wide settings."""

from hypothesis import settings

# No per-example deadline: the first example of a property test may compile numba kernels
# (seconds), and on a shared 2-core machine timings say nothing about correctness.
settings.register_profile("evgrid", deadline=None)
settings.load_profile("evgrid")
