"""Closed-form 3x3 stack operations against numpy's general ones."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from ffcomp.linalg3 import gram3, inv3, matvec3, rmatvec3, solve3


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 50))
def test_stack_ops_match_numpy(seed, n):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, 3, 3)) + 3 * np.eye(3)  # well conditioned
    x = rng.normal(size=(n, 3))
    B = rng.normal(size=(n, 3, 2))
    np.testing.assert_allclose(inv3(A), np.linalg.inv(A), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(solve3(A, B), np.linalg.solve(A, B), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(matvec3(A, x), np.einsum("nij,nj->ni", A, x), rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(rmatvec3(A, x), np.einsum("nji,nj->ni", A, x), rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(gram3(A), np.einsum("nki,nkj->nij", A, A), rtol=1e-13, atol=1e-13)
