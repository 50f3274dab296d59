"""The toe model's analytic derivatives (``tasks.weld_fits._toe_jacobian``), which every toe fit
uses instead of scipy's differences, against central differences of the model itself."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tasks.weld_fits import _toe_jacobian, _toe_model


@pytest.mark.parametrize("undercut", [False, True])
@pytest.mark.parametrize("theta_deg, r, k", [(25.0, 0.8, 0.05), (8.0, 3.0, 0.0), (70.0, 0.05, 1.5)])
def test_the_toe_models_derivatives_are_its_differences(undercut, theta_deg, r, k):
    p = np.array([0.1, math.radians(theta_deg), r, k] + ([0.1, 0.3, 0.4] if undercut else []))
    w = np.sort(np.random.default_rng(0).uniform(-3.0, 3.0, 400))
    analytic = _toe_jacobian(p, w, undercut)
    assert analytic.shape == (len(w), len(p))
    eps = 1e-7
    steps = eps * np.eye(len(p))
    central = np.column_stack([(_toe_model(p + e, w, undercut) - _toe_model(p - e, w, undercut)) / (2 * eps)
                               for e in steps])
    # measured: 1e-9 or less (the points are not on the model's kinks: flank to fillet, fillet to plate)
    np.testing.assert_allclose(analytic, central, atol=1e-6)
    assert np.count_nonzero(analytic[:, 2]) > 0  # some points on the fillet: its radius is seen
