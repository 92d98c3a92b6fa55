"""Shared test data (not a test module): the thesis §4.1.3 plant under the state feedback
u = L0 x, the uncertainty direction on entries (1,3), (2,2) of A, an inconsistent initial
state, and a second-order LTI observer driven by y.

Used by test_study_exact.py and test_study_exponential.py, which check the batched exact
and exponential steppers against independent SciPy references on this loop.
"""

import jax
import jax.numpy as jnp
import numpy as np

from fojax.observer import AbstractObserver, LinearObserverMatrices


E = np.diag([1.0, 1.0, 1.0, 0.0])
A0 = np.array(
    [[-3.0, 2.0, 1.0, 1.0], [1.0, -2.0, 1.0, -2.0], [3.0, 0.0, 1.0, -0.5], [-1.0, -2.0, 0.0, 1.0]]
)
B0 = np.array([[1.0, 0.0], [0.5, -1.0], [0.0, 1.0], [0.0, 0.0]])
C0 = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 0, 1.0]])
L0 = np.array([[-8.95, -26.07, 12.1, -4.85], [1.71, 1.31, -3.51, -0.16]])
ACL = A0 + B0 @ L0
DA = np.zeros((4, 4))
DA[0, 2] = DA[1, 1] = 1.0
X0 = np.array([16.0, -1.0, 3.0, 7.0])  # x4 inconsistent: projected (slow part kept)
AO = np.array([[-2.0, 0.5], [0.0, -3.0]])
BY = np.array([[1.0, 0.0, 0.2], [0.0, 1.0, -0.1]])

class LTIObserver(AbstractObserver):
    """xi' = A xi + By y, output xi (2 states), started at xi0."""

    A: jax.Array
    By: jax.Array
    xi0: jax.Array

    @property
    def state_size(self):
        return 2

    @property
    def output_size(self):
        return 2

    def vector_field(self, t, xi, u, y):
        return self.A @ xi + self.By @ y

    def output(self, t, xi, u, y):
        return xi

    def initial_state(self):
        return self.xi0

    def linear_matrices(self):
        z = jnp.zeros
        return LinearObserverMatrices(self.A, z((2, 2)), self.By, jnp.eye(2), z((2, 2)), z((2, 3)))
