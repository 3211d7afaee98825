"""How far two float sums of the same terms can differ when only their order differs.

drjit's LLVM backend accumulates scatter-adds (the film's pixel sums, every gradient of the
renderer's backward pass) from several threads; which thread adds first depends on the
scheduler, so two runs of the same render sum the same terms in different orders (drjit's
docs: "Atomic additions are subject to non-deterministic rounding errors"). A test that
compares two such results must allow for that, and no more:

- Worst case (Higham, *Accuracy and Stability of Numerical Algorithms*, eq. 4.4): a recursive
  sum of n terms in any order is within (n - 1) u sum|c_i| of the exact sum (u: the unit
  roundoff, 2^-24 for float32), so two orders differ by at most 2 (n - 1) u sum|c_i|. For
  terms of one sign (a pixel's radiance samples) sum|c_i| is the result itself: a rigorous
  relative tolerance.
- Typical (rounding errors as a random walk): sqrt(n) u sum|c_i|. The worst case grows with n
  and becomes useless for the thousands of terms of a gradient; there a test takes a multiple
  of this scale instead and says which.

Bit equality is a different property ("zero offset is the collocated kernel bit for bit"):
tests of it run with the ``drjit_single_thread`` fixture (tests/conftest.py), where the order
is fixed.
"""

from __future__ import annotations

import math

U32 = 2.0**-24  # unit roundoff of float32 (np.finfo(np.float32).eps / 2)


def reorder_bound(n_terms: int, magnitude: float = 1.0, u: float = U32) -> float:
    """Largest difference between two sums of the same ``n_terms`` terms in two orders, for
    terms with sum|c_i| = ``magnitude``: 2 (n - 1) u magnitude."""
    return 2.0 * max(int(n_terms) - 1, 0) * u * float(magnitude)


def reorder_scale(n_terms: int, magnitude: float = 1.0, u: float = U32) -> float:
    """The typical size of that difference: sqrt(n) u magnitude (a random walk of roundings)."""
    return math.sqrt(max(int(n_terms), 1)) * u * float(magnitude)


# d sRGB / d linear times the linear value, at most, for linear values in [0, 1]: in the power
# segment s = 1.055 L^(1/2.4) - 0.055 gives L ds/dL = (1.055 / 2.4) L^(1/2.4) <= 0.44; in the
# linear segment (L <= 0.0031308) it is 12.92 L <= 0.041. So a relative error e of the linear
# value changes the sRGB value by at most 0.44 e (values clipped at 1 do not change).
SRGB_RELATIVE_SLOPE = 1.055 / 2.4
