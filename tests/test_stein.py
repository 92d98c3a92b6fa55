"""The one Stein certificate of a disk (`fojax.design._stein`): host (SciPy or Smith's
doubling) and traced, as used by the Riccati route, the finite-time fallback, the
unknown-input preconditioner and the tuning parameterizations.

Oracles: the closed form of the scalar equation, ``x = 1 / (1 - ((a - α)/τ)²)``; the
residual of the Stein equation itself; and the Schur-complement equivalence with the
disk's region LMI evaluated by `fojax.design.Disk.lmi_matrix` (``eigvalsh``).
"""

import numpy as np
import pytest

from fojax.design import Disk, host_stein_certificate, stein_certificate


@pytest.mark.parametrize("method", ["scipy", "doubling"])
def test_scalar_closed_form(method):
    for a, c, r in [(-1.5, -2.0, 1.0), (-2.9, -2.0, 1.0), (0.3, 0.0, 0.5)]:
        x = host_stein_certificate(np.array([[a]]), c, r, method=method)
        assert np.isclose(x[0, 0], 1.0 / (1.0 - ((a - c) / r) ** 2), rtol=1e-12)


@pytest.mark.parametrize("method", ["scipy", "doubling"])
def test_matrix_residual_and_region_lmi(method):
    rng = np.random.default_rng(0)
    region = Disk(-3.0, 2.0)
    V = rng.standard_normal((4, 4))
    A = V @ np.diag([-2.0, -2.5, -3.5, -4.2]) @ np.linalg.inv(V)  # non-normal, inside the disk
    X = host_stein_certificate(A, region.center, region.radius, method=method)
    Ab = (A - region.center * np.eye(4)) / region.radius
    assert np.abs(Ab.T @ X @ Ab - X + np.eye(4)).max() <= 1e-9 * np.abs(X).max()
    assert np.linalg.eigvalsh(X).min() >= 1.0 - 1e-9  # X ⪰ I
    assert np.linalg.eigvalsh(region.lmi_matrix(X, X @ A)).max() < 0
    traced = np.asarray(stein_certificate(A, region.center, region.radius))
    assert np.allclose(traced, X, rtol=1e-9, atol=1e-9 * np.abs(X).max())


def test_outside_the_disk_is_not_a_certificate_and_overflow_is_named():
    X = host_stein_certificate(np.array([[0.5]]), -2.0, 1.0)  # eigenvalue outside the disk
    assert not np.linalg.eigvalsh(X).min() > 0
    from fojax.errors import DesignVerificationError

    with pytest.raises(DesignVerificationError, match="overflows float64"):
        host_stein_certificate(np.array([[1e300, 1e300], [0.0, 0.5]]), method="doubling")
    notes = []
    assert host_stein_certificate(np.zeros((0, 0)), notes=notes).shape == (0, 0) and notes == []
    with pytest.raises(ValueError, match="method must be one of"):
        host_stein_certificate(np.eye(1) * 0.1, method="lu")
