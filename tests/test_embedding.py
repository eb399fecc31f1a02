"""Regular-simplex embedding of affine coordinates (Sec. 5)."""
import itertools

import numpy as np
import pytest

from flatserve.embedding import embed, regular_simplex, unembed
from flatserve.errors import InvalidInputError


@pytest.mark.parametrize("m", [2, 3, 5, 8, 13])
def test_regular_simplex(m):
    V = regular_simplex(m)
    assert V.shape == (m, m - 1)
    np.testing.assert_allclose(V.sum(axis=0), 0, atol=1e-12)  # centred
    dists = [np.linalg.norm(V[i] - V[j]) for i, j in itertools.combinations(range(m), 2)]
    np.testing.assert_allclose(dists, dists[0], rtol=1e-12)  # regular


@pytest.mark.parametrize("m", [2, 5, 13])
def test_embed_unembed_roundtrip_and_isometry(m):
    rng = np.random.default_rng(m)
    w = rng.normal(size=(100, m))
    w /= w.sum(axis=1, keepdims=True)
    x = embed(w)
    assert x.shape == (100, m - 1)
    np.testing.assert_allclose(unembed(x), w, atol=1e-10)
    # vertices of the simplex are the embeddings of the unit coordinates
    np.testing.assert_allclose(embed(np.eye(m)), regular_simplex(m), atol=1e-14)
    # distances on the hyperplane sum w = 1 are preserved (isometry)
    np.testing.assert_allclose(np.linalg.norm(x[1:] - x[:-1], axis=1),
                               np.linalg.norm(w[1:] - w[:-1], axis=1), rtol=1e-10)
    # barycentric combination commutes with embedding
    lam = rng.random((100, 1))
    np.testing.assert_allclose(embed(lam * w + (1 - lam) * w[::-1]),
                               lam * x + (1 - lam) * x[::-1], atol=1e-12)


@pytest.mark.parametrize("call,arg", [
    (lambda: regular_simplex(1), "m"),
    (lambda: embed([[np.nan, 1.0]]), "w"),
    (lambda: embed([1.0, 0.0]), "w"),
    (lambda: unembed([[np.inf]]), "x"),
])
def test_bad_input(call, arg):
    with pytest.raises(InvalidInputError) as e:
        call()
    assert e.value.argument == arg


@pytest.mark.parametrize("m", [2, 5, 13])
def test_a_row_gets_the_same_bits_whatever_its_batch(m):
    """A sample and a query at the same flat must land on the same point: embed
    and unembed of a row do not depend on the rows beside it (a BLAS product
    rounds one row and many rows differently)."""
    rng = np.random.default_rng(m)
    w, y = rng.normal(size=(700, m)), rng.normal(size=(700, m - 1))
    x, back = embed(w), unembed(y)
    for n in (1, 2, 3, 7, 64, 699):
        rows = rng.choice(700, n, replace=False)
        assert np.array_equal(embed(w[rows]), x[rows])
        assert np.array_equal(unembed(y[rows]), back[rows])
