import numpy as np
import pytest

from models.tactile.windows import n_windows, sliding_windows


@pytest.mark.parametrize(
    ("n", "length", "hop", "expected"),
    [(500, 25, 12, 40), (499, 500, 500, 0), (500, 500, 500, 1), (1499, 500, 500, 2), (1500, 500, 250, 5)],
)
def test_n_windows(n, length, hop, expected):
    assert n_windows(n, length, hop) == expected


def test_sliding_windows_are_views_with_the_right_content():
    x = np.arange(30.0).reshape(10, 3)
    w = sliding_windows(x, 4, 3, axis=0)
    assert w.shape == (3, 3, 4)  # (windows, columns, samples)
    assert np.shares_memory(w, x)
    np.testing.assert_array_equal(w[2], x[6:10].T)
    y = np.arange(2 * 100.0).reshape(2, 100)
    v = sliding_windows(y, 25, 12, axis=1)
    assert v.shape == (2, 7, 25)
    np.testing.assert_array_equal(v[1, 3], y[1, 36:61])


def test_bad_arguments():
    with pytest.raises(ValueError, match="hop"):
        n_windows(10, 4, 0)
    with pytest.raises(ValueError, match="length"):
        n_windows(10, 0, 1)
    with pytest.raises(ValueError, match="a window needs 4"):
        sliding_windows(np.zeros(3), 4, 1)


@pytest.mark.parametrize(("shape", "axis"), [((37,), 0), ((37, 3), 0), ((2, 37), 1), ((2, 37, 3), -2), ((37, 2), -2)])
@pytest.mark.parametrize(("length", "hop"), [(5, 1), (8, 3), (18, 2)])
@pytest.mark.parametrize("step", [1, 2])  # 2: a strided (non-contiguous) input
def test_sliding_windows_match_numpys_view(shape, axis, length, hop, step):
    big = list(shape)
    big[axis % len(shape)] *= step
    base = np.arange(np.prod(big), dtype=float).reshape(big)
    index = [slice(None)] * base.ndim
    index[axis % base.ndim] = slice(None, None, step)
    x = base[tuple(index)]
    ref = np.lib.stride_tricks.sliding_window_view(x, length, axis=axis)
    every = [slice(None)] * ref.ndim
    every[axis % x.ndim] = slice(None, None, hop)
    w = sliding_windows(x, length, hop, axis=axis)
    np.testing.assert_array_equal(w, ref[tuple(every)])
    assert np.shares_memory(w, base)
    assert not w.flags.writeable
