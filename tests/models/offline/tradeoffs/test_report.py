from models.offline.tradeoffs.report import _coverage


def test_a_coverage_cell_carries_its_texture_level_interval():
    assert _coverage({"empirical": 0.9, "empirical_ci": [0.851, 0.95]}) == "90.0% [85.1%, 95.0%]"
    # rows of a run made before the interval was stored: the mean alone, not a made-up interval
    assert _coverage({"empirical": 0.9}) == "90.0%"
