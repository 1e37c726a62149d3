import pytest

from models.offline.evaluation.families import LEAVE_OUT, family_of, left_out_with, with_siblings


@pytest.mark.parametrize(
    ("texture", "family"),
    [
        ("carpet_3", "carpet"),
        ("sandpaper_100", "sandpaper"),
        ("paper_plate_2", "paper_plate"),
        ("abs_plastic", "abs_plastic"),  # no trailing number: a family of its own
        ("t017", "t017"),  # hassan2023's names: every texture its own family
        ("grit_2a", "grit_2a"),  # only a number suffix separated by "_" counts
    ],
)
def test_family_of_known_answers(texture, family):
    assert family_of(texture) == family


@pytest.mark.parametrize("bad", ["", "_3", None, 7])
def test_family_of_refuses_names_that_name_no_family(bad):
    with pytest.raises(ValueError, match="texture name"):
        family_of(bad)


def test_left_out_with_texture_keeps_nothing_else_out():
    assert left_out_with(["carpet_1", "carpet_3", "abs"], "texture") == [(), (), ()]


def test_left_out_with_family_names_each_textures_siblings():
    textures = ["carpet_1", "abs", "carpet_3", "sandpaper_100", "carpet_4", "sandpaper_220"]
    assert left_out_with(textures, "family") == [(2, 4), (), (0, 4), (5,), (0, 2), (3,)]
    assert with_siblings(textures) == [0, 2, 3, 4, 5]
    assert LEAVE_OUT == ("texture", "family")


def test_left_out_with_refuses_an_unknown_scheme():
    with pytest.raises(ValueError, match="leave_out must be one of"):
        left_out_with(["a"], "group")
