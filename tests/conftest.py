"""Suite-wide settings: property tests draw the same examples on every run (fixed seeds), so a
green run on one machine is green on CI and a failure reproduces. No example has a deadline, and slow
data generation is no failure: a host busy with other work makes both slow, and neither says anything
about the code (speed is measured in benchmarks/)."""

from hypothesis import HealthCheck, settings

settings.register_profile("fixed-seed", derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("fixed-seed")
