"""Named simulation presets, one seed each, reproducible bit for bit.

- ``ci``: a short coupon, coarse sensor, 14 passes, both setups: seconds; for tests.
- ``demo``: the paper's specimen and Table I scan plan (32 passes) at a coarser sensor
  resolution: a few million points, well under a minute.
- ``tjoint``: a T-joint (260 x 120 x 12 mm base, 10 x 60 mm stem, two convex fillet welds), two
  setups (stem up; turned over, the stem between the support blocks) whose only shared surfaces are
  the base plate's 12 mm walls: 17 passes, about 2.3 M points.
- ``tjoint-single``: the same T-joint in one setup (stem up): 10 passes.
- ``cruciform``: a cruciform joint: the T-joint's plates with a second stem on the base plate's
  other face, in the same plane, four convex fillet welds; two setups (each with one stem up, the
  other hanging between the support blocks) whose only shared surfaces are again the base plate's
  walls: 20 passes. The same seed as ``tjoint``: its upper fillets are the T-joint's, drawn first.
- ``paper``: Table I at full resolution (2048 points per profile at 0.02 mm, 0.1 mm between
  profiles at 15 mm/s): hundreds of millions of points, written pass by pass.
"""

from __future__ import annotations

from schemas.simulation import (FixtureConfig, TrueMeshConfig, PlacementConfig, RobotConfig, ScanPlanConfig,
                                ScannerConfig, SimulationConfig, SpecimenConfig, StickerConfig, TJointConfig,
                                WeldConfig, WidthPass)

__all__ = ["PRESETS", "preset_config", "UnknownPresetError"]


class UnknownPresetError(ValueError):
    pass


def _paper() -> SimulationConfig:
    return SimulationConfig(preset="paper", seed=2020, sample_id="sim-paper-2020",
                            weld=WeldConfig(treatment="hfmi-treated"), chunk_profiles=256)


def _demo() -> SimulationConfig:
    return SimulationConfig(
        preset="demo", seed=7, sample_id="sim-demo-0007",
        weld=WeldConfig(treatment="hfmi-treated"),
        scanner=ScannerConfig(points_per_profile=192, x_spacing_mm=0.2133),
        robot=RobotConfig(profile_spacing_mm=0.5),
        mesh=TrueMeshConfig(plate_dx_mm=1.0, weld_dx_mm=0.1, toe_dx_mm=0.05, across_nodes=500, wall_rows=21),
        chunk_profiles=256,
    )


def _ci() -> SimulationConfig:
    return SimulationConfig(
        preset="ci", seed=11, sample_id="sim-ci-0011",
        specimen=SpecimenConfig(length_mm=240.0, grip_width_mm=60.0, gauge_width_mm=44.0, gauge_length_mm=60.0,
                                transition_radius_mm=40.0, thickness_mm=20.0),
        weld=WeldConfig(treatment="as-welded", cap_height_mm=(1.5, 3.0), cap_width_mm=(10.0, 13.0),
                        flank_angle_deg=(30.0, 60.0), undercut_probability=0.5),
        stickers=StickerConfig(diameter_mm=5.0, n_fixture=4),
        fixture=FixtureConfig(plate_size_mm=(400.0, 220.0, 10.0), block_size_mm=(30.0, 30.0, 25.0),
                              block_centres_x_mm=(-90.0, 90.0)),
        scanner=ScannerConfig(points_per_profile=128, x_spacing_mm=0.32),
        robot=RobotConfig(profile_spacing_mm=0.32),
        plan=ScanPlanConfig(vertical_offsets_mm=[-15.0, 0.0, 15.0], side_rolls_deg=[45.0],
                            width_passes=[WidthPass(x_mm=-20.0), WidthPass(x_mm=20.0)]),
        placement=PlacementConfig(translation_mm=5.0, yaw_deg=2.0),
        mesh=TrueMeshConfig(plate_dx_mm=1.0, weld_dx_mm=0.15, toe_dx_mm=0.08, across_nodes=160, wall_rows=9),
        chunk_profiles=128,
    )


def _tjoint(setups: list[str], sample_id: str, preset: str, *, stems: str = "one") -> SimulationConfig:
    return SimulationConfig(
        preset=preset, seed=41, sample_id=sample_id,
        tjoint=TJointConfig(stems=stems),
        weld=WeldConfig(treatment="as-welded", toe_radius_mm=(0.5, 2.0), undercut_probability=0.0),
        stickers=StickerConfig(diameter_mm=5.0, n_fixture=8),
        fixture=FixtureConfig(plate_size_mm=(420.0, 320.0, 10.0), block_size_mm=(30.0, 60.0, 80.0),
                              block_centres_x_mm=(-105.0, 105.0)),
        scanner=ScannerConfig(points_per_profile=256, x_spacing_mm=0.32),
        robot=RobotConfig(profile_spacing_mm=0.32),
        plan=ScanPlanConfig(setups=setups, margin_mm=40.0),
        placement=PlacementConfig(translation_mm=5.0, yaw_deg=2.0),
        mesh=TrueMeshConfig(plate_dx_mm=1.0, weld_dx_mm=0.1, toe_dx_mm=0.05, wall_rows=13),
        chunk_profiles=128,
    )


PRESETS = {"ci": _ci, "demo": _demo, "paper": _paper,
           "tjoint": lambda: _tjoint(["top", "bottom"], "sim-tjoint-0041", "tjoint"),
           "tjoint-single": lambda: _tjoint(["top"], "sim-tjoint-single-0041", "tjoint-single"),
           "cruciform": lambda: _tjoint(["top", "bottom"], "sim-cruciform-0041", "cruciform", stems="both")}


def preset_config(name: str) -> SimulationConfig:
    try:
        return PRESETS[name]()
    except KeyError:
        raise UnknownPresetError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}") from None
