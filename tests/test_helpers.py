"""`tests/helpers.py`: the eigenvalue-set comparison every spectral test relies on.

Oracle: hand-built sets whose correct verdict is evident (permutations of one set, a
conjugate pair in either order, sets that differ in one value, a case where pairing each
value with its nearest neighbour fails but a one-to-one matching exists).
"""

import numpy as np
import pytest
from helpers import assert_eigenvalues_match, match_eigenvalues, spectral_distance


def test_conjugate_pair_in_either_order_matches():
    # the issue-17 failure: real parts 1 ulp apart, so np.sort_complex swaps the pair
    re = -0.7
    a = np.array([re + 0.05j, np.nextafter(re, 0) - 0.05j, -2.0])
    b = np.array([-2.0, re - 0.05j, re + 0.05j])
    assert not np.allclose(np.sort_complex(a), np.sort_complex(b), rtol=1e-8)  # the pitfall
    aligned = assert_eigenvalues_match(a, b, rtol=1e-12)
    np.testing.assert_allclose(aligned, b, rtol=1e-12)


def test_optimal_not_greedy_matching():
    # pairing 1.04 with its nearest value 1.0 leaves 1.1 for 0.95 (0.15 > 0.1); the only
    # matching within 0.1 is 1.04 -> 1.1, 0.95 -> 1.0
    a = np.array([1.04, 0.95])
    b = np.array([1.0, 1.1])
    np.testing.assert_allclose(assert_eigenvalues_match(a, b, atol=0.1, rtol=0.0), [0.95, 1.04])
    _, ok, _ = match_eigenvalues(np.array([1.0, 1.0]), b, atol=0.05, rtol=0.0)
    assert not ok  # a multiset: 1.0 twice does not cover 1.1


def test_different_sets_fail_with_both_sets_in_the_message():
    with pytest.raises(AssertionError, match=r"(?s)1\.5.*actual :.*desired:") as ei:
        assert_eigenvalues_match([-1.0, 1.5], [-1.0, 1.0], rtol=1e-6, err_msg="the loop")
    assert "the loop" in str(ei.value) and "|diff| 5.000e-01" in str(ei.value)
    with pytest.raises(AssertionError, match="2 actual values but 3 desired"):
        assert_eigenvalues_match([1.0, 2.0], [1.0, 2.0, 3.0])
    with pytest.raises(AssertionError, match="non-finite"):
        assert_eigenvalues_match([np.nan], [1.0])


def test_per_value_tolerance_and_zero_tolerance():
    assert_eigenvalues_match([10.05, 1.0], [1.0, 10.0], atol=[0.0, 0.1], rtol=0.0)
    with pytest.raises(AssertionError):
        assert_eigenvalues_match([10.0, 1.05], [1.0, 10.0], atol=[0.0, 0.1], rtol=0.0)
    assert_eigenvalues_match([2.0, 1.0], [1.0, 2.0], rtol=0.0)  # exact, any order
    assert_eigenvalues_match([], [])


def test_spectral_distance_is_the_bottleneck_matching():
    # {0, i, 2i} vs {0, i, 1}: the pairing of least total distance keeps 0-0 and i-i and
    # leaves 2i-1 (sqrt 5); the bottleneck pairing 0-1, i-0, 2i-i has every distance 1
    assert spectral_distance([0.0, 1j, 2j], [0.0, 1j, 1.0]) == pytest.approx(1.0)
    assert spectral_distance([1.04, 0.95], [1.0, 1.1]) == pytest.approx(0.06)
    assert spectral_distance([1.0 + 1.0j, 1.0 - 1.0j], [1.0 - 1.0j, 1.0 + 1.0j]) == 0.0
    assert spectral_distance([1.0], [1.0, 2.0]) == np.inf
