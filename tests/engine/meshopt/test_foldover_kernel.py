"""The untangling's compiled bookkeeping is NumPy's fancy indexing and np.add.at, bit for bit."""

from __future__ import annotations

import numpy as np

from kneegui.meshopt.foldover_kernel import add_at_rows, gather_rows, scatter_scaled


def test_scatter_gather_and_add_at_are_numpys_to_the_last_bit():
    rng = np.random.default_rng(7)
    coords = rng.normal(size=(500, 3))
    rows = rng.choice(500, 120, replace=False)
    flat = rng.normal(size=360)
    scale = rng.uniform(0.1, 3.0, (120, 1))

    work = coords.copy()
    scatter_scaled(work, rows, flat, scale)
    expected = coords.copy()
    expected[rows] = flat.reshape(-1, 3) * scale
    np.testing.assert_array_equal(work, expected)

    out = np.empty((120, 3))
    gather_rows(work, rows, out)
    np.testing.assert_array_equal(out, expected[rows])

    # repeated rows add in the order given, as np.add.at does (the order changes the bits)
    repeated = rng.integers(0, 20, 400)
    values = rng.normal(size=(400, 3)) * 10.0 ** rng.integers(-8, 8, (400, 1))
    grad = rng.normal(size=(500, 3))
    reference = grad.copy()
    np.add.at(reference, repeated, values)
    add_at_rows(grad, repeated, values)
    np.testing.assert_array_equal(grad, reference)
