"""Compiled shading of a GelSight image's tilted pixels (numba): the renderer's hot path.

Every tilted pixel of a contact (``sim.gelsight``, step 3) reads its slope bin's calibration
polynomial in its position and adds the colour it gives, less the flat gel's, to the image's
change. In NumPy that was a gather of each pixel's 3 x 6 coefficients, an einsum and an indexed
add: 0.29 of the 0.53 ms one 100 x 100 prior image took, in a dozen short calls that hold
Python's lock between them. Here it is one loop outside the lock: the same float32 arithmetic,
so the same images (bit-identical to the einsum on the AVX-512 machine the figures come from;
docs/measurements.md).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def add_tilted_colour(
    change: np.ndarray,
    tilted: np.ndarray,
    bins: np.ndarray,
    coeffs: np.ndarray,
    terms: np.ndarray,
    flat_colour: np.ndarray,
    gain: np.float32,
) -> None:
    """change[p] += gain * (colour of pixel p in its slope bin - flat_colour[p]), in place, for
    every pixel p = tilted[j] in slope bin bins[j]: ``change`` pixels x 3 float32 levels,
    ``coeffs`` bins x 3 x 6 and ``terms`` pixels x 6 the calibration polynomial's coefficients
    and position terms (float32). The six products are summed as NumPy's einsum sums them with
    AVX-512 lanes, ((t0 + t4) + (t1 + t5)) + (t2 + t3), so that the images match the
    renderer's NumPy form there; on other vector widths the two differ by float32 rounding."""
    for j in range(tilted.shape[0]):
        pixel, b = tilted[j], bins[j]
        for c in range(3):
            t0 = coeffs[b, c, 0] * terms[pixel, 0]
            t1 = coeffs[b, c, 1] * terms[pixel, 1]
            t2 = coeffs[b, c, 2] * terms[pixel, 2]
            t3 = coeffs[b, c, 3] * terms[pixel, 3]
            t4 = coeffs[b, c, 4] * terms[pixel, 4]
            t5 = coeffs[b, c, 5] * terms[pixel, 5]
            colour = ((t0 + t4) + (t1 + t5)) + (t2 + t3)
            change[pixel, c] += gain * (colour - flat_colour[pixel, c])
