"""Suite-wide settings: property tests draw the same examples on every run (fixed seeds), so a
green run on one machine is green on CI and a failure reproduces."""

from hypothesis import settings

settings.register_profile("fixed-seed", derandomize=True)
settings.load_profile("fixed-seed")
