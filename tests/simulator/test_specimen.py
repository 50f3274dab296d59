"""The virtual specimen: a closed, outward mesh of the right volume; weld caps that have the
geometry they were drawn with."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from schemas.simulation import TrueMeshConfig, SpecimenConfig, WeldConfig
from simulator.specimen import build_specimen


@pytest.fixture(scope="module")
def specimen():
    return build_specimen(SpecimenConfig(), WeldConfig(treatment="hfmi-treated"),
                          TrueMeshConfig(across_nodes=200, toe_dx_mm=0.05, weld_dx_mm=0.1), np.random.default_rng(3))


def test_mesh_is_closed_and_outward(specimen):
    tri = specimen.mesh.triangles.astype(np.int64)
    directed = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    n = len(specimen.mesh.vertices)
    keys = directed[:, 0] * n + directed[:, 1]
    assert np.unique(keys).size == keys.size  # consistently oriented
    undirected = np.sort(directed, axis=1)
    _, counts = np.unique(undirected[:, 0] * n + undirected[:, 1], return_counts=True)
    assert np.all(counts == 2)  # closed, manifold
    cfg = specimen.config
    xs = np.linspace(-cfg.length_mm / 2, cfg.length_mm / 2, 20001)
    plate = np.trapezoid(2 * specimen.half_width(xs), xs) * cfg.thickness_mm
    assert specimen.mesh.signed_volume_mm3() > 0
    assert_allclose(specimen.mesh.signed_volume_mm3(), plate, rtol=0.01)


def test_dog_bone_outline():
    cfg = SpecimenConfig()
    spec = build_specimen(cfg, WeldConfig(), TrueMeshConfig(across_nodes=20), np.random.default_rng(0))
    assert_allclose(spec.half_width(np.array([0.0, 89.0, 285.0])), [35.0, 35.0, 50.0])
    xs = np.linspace(90, 200, 500)
    assert np.all(np.diff(spec.half_width(xs)) >= -1e-12)  # widens monotonically toward the grips


def test_weld_cap_has_its_drawn_geometry(specimen):
    cap = specimen.weld_top
    for y in (-30.0, 0.0, 25.0):
        ya = np.array([y])
        centre, h, w = cap.centre(ya)[0], cap.height(ya)[0], cap.width(ya)[0]
        z_mid, _ = cap.height_mm(np.array([centre]), ya)
        assert abs(z_mid[0] - h) <= cap.ripple_amplitude_mm + 1e-9
        far, _ = cap.height_mm(np.array([centre - w / 2 - 8, centre + w / 2 + 8]), np.array([y, y]))
        assert_allclose(far, 0.0, atol=1e-9)
        # HFMI groove: deepest point is the drawn depth below the plate, beside each toe
        for side, sign in ((0, -1), (1, 1)):
            u = centre + sign * np.linspace(w / 2 - 1, w / 2 + cap.groove_width[side](ya)[0], 4000)
            z, _ = cap.height_mm(u, np.full(u.shape, y))
            assert_allclose(z.min(), -cap.groove_depth[side](ya)[0], atol=0.01)


def test_flank_angle_is_the_drawn_one_and_is_measured():
    plain = WeldConfig(treatment="as-welded", undercut_probability=0.0, ripple_amplitude_mm=(0.0, 0.0))
    specimen = build_specimen(SpecimenConfig(), plain, TrueMeshConfig(across_nodes=20), np.random.default_rng(5))
    cap = specimen.weld_top
    y = 10.0
    ya = np.array([y])
    for side, sign in ((0, -1), (1, 1)):
        drawn = cap.flank_deg[side](ya)[0]
        effective = cap.effective_flank_deg(ya, side)[0]
        if cap.shape_exponent(ya, side)[0] > 1.2:  # not limited by the minimum shape exponent
            assert_allclose(effective, drawn, rtol=1e-9)
        # the measured slope just inside the toe fillet approaches the effective flank angle
        half, centre = cap.width(ya)[0] / 2, cap.centre(ya)[0]
        r = cap.toe_radius[side](ya)[0]
        d = r * np.tan(np.radians(effective) / 2)
        u = half - d - 0.02
        xs = centre + sign * np.array([u - 0.01, u + 0.01])
        z, _ = specimen.weld_top.height_mm(xs, np.full(2, y))
        slope = np.degrees(np.arctan(abs(z[1] - z[0]) / 0.02))
        assert abs(slope - effective) < 3, (side, slope, effective)  # the cap is convex
