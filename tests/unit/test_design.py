"""ODAR design optimisation (thesis sec. 2.2.2): metrics, flow volume, grid search, the [rotors.geometry] table."""

from __future__ import annotations

import json
import tomllib
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from companion.configfile import ConfigError, build, dump_toml, to_dict
from companion.skeleton.rotors import RotorGeometry, RotorGeometryConfig, RotorParams
from link_firmware_sim.config import VehicleSetup
from link_firmware_sim.design import (
    DesignProblem,
    FlowVolume,
    OdarDesign,
    SearchGrid,
    aero_clearance_m,
    evaluate,
    flow_radius_m,
    force_min,
    force_min_weighted,
    force_min_xz,
    search,
    torque_generators,
    torque_min,
    torque_min_weighted,
)
from link_firmware_sim.design.__main__ import main as design_main
from link_firmware_sim.design.search import (
    mirror_directions,
    position_candidates,
    search_directions,
)
from sitl.scenario import load_scenario

TABLE = RotorGeometry.odar(sigma1=1)  # Table 2.1 as printed
SCENARIO = "configs/sitl/odar/single_odar_pitch45.toml"
TINY = SearchGrid(direction_step_deg=3.0, x_count=2, radius_count=1, angle_step_deg=45.0)

finite = st.floats(-1.0, 1.0, allow_nan=False)
vec3 = st.tuples(finite, finite, finite).filter(lambda v: np.linalg.norm(v) > 0.1)
directions4 = st.lists(vec3, min_size=4, max_size=4).map(lambda v: np.array(v) / np.linalg.norm(v, axis=1)[:, None])
positions4 = st.lists(st.tuples(st.floats(-0.4, 0.4), st.floats(-0.3, 0.3), st.floats(-0.3, 0.3)), min_size=4,
                      max_size=4).map(np.array)
rotations = st.tuples(finite, finite, finite).map(lambda v: Rotation.from_rotvec(3.0 * np.array(v)).as_matrix())


# --- Table 2.1 -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name, thesis",
    [("f_min", 2.04), ("f_min_xz", 3.85), ("m_min", 0.894)],
)
def test_table_2_1_reproduces_the_thesis_metrics_within_2_percent(name, thesis):
    value = getattr(evaluate(TABLE), name)
    assert value == pytest.approx(thesis, rel=0.02)


def test_table_2_1_is_feasible_and_clear_of_the_flow():
    m = evaluate(TABLE)
    assert m.d_aero_m >= 0.12 and m.feasible
    assert m.weight_ok and m.f_min_weighted >= DesignProblem().weight_lambda
    # the weighted force with W_y = 0.4 equals the sagittal-plane figure here (the binding facet lies in XZ)
    assert m.f_min_weighted == pytest.approx(m.f_min_xz, rel=1e-9)


def test_the_modified_design_loses_a_few_percent_of_torque_and_gains_2_11():
    """Sec. 2.4.1: sigma_1 = -1 keeps U (same F_min) and reduces M_min by 3.6 % (here 3.3 %)."""
    printed, modified = evaluate(TABLE), evaluate(RotorGeometry.odar(sigma1=-1))
    assert modified.f_min == printed.f_min
    assert 0.02 < 1 - modified.m_min / printed.m_min < 0.05
    assert modified.null_structure and not printed.null_structure


# --- properties of F_min, M_min ------------------------------------------------------------------


def _hull_inradius(points: np.ndarray) -> float:
    """Least facet distance of the convex hull of ``points`` (Qhull): an independent inscribed radius."""
    return float(-ConvexHull(points).equations[:, 3].max())


@settings(max_examples=40, deadline=None)
@given(directions4, positions4, st.lists(st.sampled_from([-1, 1]), min_size=4, max_size=4))
def test_f_min_and_m_min_are_the_inscribed_radii_of_the_feasible_volumes(u, r, spin):
    """(2.2)/(2.3) against Qhull's facets of V_F, V_M (the hull of all 2^4 corner sums, Fig. 2-2)."""
    design = OdarDesign(RotorGeometry.from_pairs(u, r, spin), DesignProblem(thrust_max_n=1.0))
    m = design.metrics()
    for points, value in ((design.force_volume_vertices_n(), m.f_min), (design.torque_volume_vertices_nm(), m.m_min)):
        assume(abs(np.linalg.det(np.cov(points.T))) > 1e-6)  # full-dimensional volume
        assert value == pytest.approx(_hull_inradius(points), rel=1e-7, abs=1e-9)


@settings(max_examples=30, deadline=None)
@given(directions4, positions4, rotations, st.lists(st.sampled_from([-1, 1]), min_size=4, max_size=4))
def test_metrics_are_invariant_under_a_rotation_of_the_whole_geometry(u, r, R, spin):
    g = RotorGeometry.from_pairs(u, r, spin)
    gr = RotorGeometry.from_pairs(u @ R.T, r @ R.T, spin)
    a, b = evaluate(g), evaluate(gr)
    for name in ("f_min", "m_min", "d_aero_m"):
        assert getattr(b, name) == pytest.approx(getattr(a, name), rel=1e-7, abs=1e-9)


@settings(max_examples=30, deadline=None)
@given(directions4, st.floats(0.1, 50.0))
def test_force_and_torque_scale_with_lambda_max(u, lam):
    t = np.cross(np.full((4, 3), 0.3), u)
    assert float(force_min(u, lam)) == pytest.approx(lam * float(force_min(u)), rel=1e-12)
    assert float(torque_min(t, lam)) == pytest.approx(lam * float(torque_min(t)), rel=1e-12)


@settings(max_examples=30, deadline=None)
@given(directions4)
def test_weights_interpolate_between_f_min_and_the_sagittal_plane(u):
    # W_y -> 0 gives F_min^xz only while the force volume's y extent is much larger than W_y (a
    # set whose y half-width is 1e-7 against W_y = 1e-6 reads its y faces: hypothesis found one)
    assume(np.abs(u[:, 1]).sum() > 1e-2)
    f, fxz = float(force_min(u)), float(force_min_xz(u))
    assert float(force_min_weighted(u, (1, 1, 1))) == pytest.approx(f, rel=1e-12)
    assert fxz >= f - 1e-12
    assert float(force_min_weighted(u, (1, 1e-6, 1))) == pytest.approx(fxz, rel=1e-4, abs=1e-9)


def test_degenerate_directions_guarantee_no_force():
    parallel = np.tile([[0.0, 0.0, 1.0]], (4, 1))
    coplanar = np.array([[1.0, 0, 0], [0, 1.0, 0], [0.6, 0.8, 0], [-0.8, 0.6, 0]])
    assert float(force_min(parallel)) == 0.0
    assert float(force_min(coplanar)) == pytest.approx(0.0, abs=1e-12)


def test_the_thin_class_agrees_with_the_functions():
    g = RotorGeometry.odar(sigma1=-1, x_scale=1.2)
    assert OdarDesign(g).metrics() == evaluate(g)
    assert _hull_inradius(OdarDesign(g).force_volume_vertices_n()) == pytest.approx(evaluate(g).f_min * 9.7)


# --- flow volume and d_aero ----------------------------------------------------------------------


def _brute_clearance(u, r, flow: FlowVolume, n_z=400, n_phi=90):
    """Distance from every r_j to a dense point cloud of every other rotor's flow volume (surface and caps)."""
    best = np.inf
    z = np.linspace(0.0, flow.length_m, n_z)
    phi = np.linspace(0, 2 * np.pi, n_phi, endpoint=False)
    for i in range(len(u)):
        e1 = np.cross(u[i], [1.0, 0, 0] if abs(u[i][0]) < 0.9 else [0, 1.0, 0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(u[i], e1)
        ra = flow_radius_m(z, flow)
        for sign in ((-1.0, 1.0) if flow.both_directions else (-1.0,)):
            rings = (r[i] + sign * z[:, None, None] * u[i]
                     + ra[:, None, None] * (np.cos(phi)[None, :, None] * e1 + np.sin(phi)[None, :, None] * e2))
            pts = np.concatenate([rings.reshape(-1, 3), r[i] + sign * z[:, None] * u[i]])
            for j in range(len(u)):
                if j != i:
                    best = min(best, np.linalg.norm(pts - r[j], axis=1).min())
    return best


@pytest.mark.parametrize("both", [True, False])
def test_aero_clearance_matches_a_brute_force_distance(both):
    flow = FlowVolume(both_directions=both)
    g = RotorGeometry.odar(sigma1=1)
    exact = float(aero_clearance_m(g.directions, g.positions_m, flow))
    brute = _brute_clearance(g.directions, g.positions_m, flow)
    assert brute >= exact - 1e-9  # the exact distance is the least
    assert brute == pytest.approx(exact, abs=2e-3)


def test_clearance_of_a_rotor_inside_the_flow_is_zero_and_upstream_only_counts_both_ways():
    # rotor 0 blows down (-z); rotor 1 sits 0.5 m above it and blows up (u_1 = -z)
    u = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    above = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.5]])
    one_way = float(aero_clearance_m(u, above, FlowVolume(both_directions=False)))
    assert one_way == pytest.approx(0.5) and float(aero_clearance_m(u, above)) == 0.0
    below = above * np.array([1.0, 1.0, -1.0])  # now each rotor sits in the other's wake
    assert float(aero_clearance_m(u, below, FlowVolume(both_directions=False))) == 0.0


def test_flow_radius_tapers():
    flow = FlowVolume()
    r = flow_radius_m(np.array([0.0, 0.5, 1.0, 1.5]), flow)
    assert r[0] == flow.radius_at_rotor_m and r[2] == pytest.approx(flow.radius_at_end_m) and np.isnan(r[3])
    assert r[0] > r[1] > r[2]


# --- grid search ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_search():
    return search(DesignProblem(), TINY)


def test_tiny_search_optimum_is_feasible_and_beats_every_grid_design(tiny_search):
    res, problem = tiny_search, DesignProblem()
    assert res.optimum_metrics.feasible and res.flyable_metrics.feasible
    assert res.flyable_metrics.null_structure and res.flyable.rotor_inertia_offdiag_m2() < 1e-9
    assert res.optimum_metrics.m_min_weighted >= res.flyable_metrics.m_min_weighted
    # brute force over the same grid, batched through the public metric functions
    u = res.directions.directions
    G = position_candidates(problem, TINY)
    rx = np.diag([1.0, -1.0, -1.0])
    r1, r2 = np.repeat(G, len(G), axis=0), np.tile(G, (len(G), 1))
    r = np.stack((r1, r2, r2 @ rx, r1 @ rx), axis=1)  # (N, 4, 3)
    spins = np.array([[1 if (k >> b) & 1 else -1 for b in range(4)] for k in range(16)])
    t = torque_generators(u[None, None], r[:, None], spins[None], problem.drag_ratio_m)  # (N, 16, 4, 3)
    score = torque_min_weighted(t, problem.torque_weight)
    u8 = np.broadcast_to(np.vstack((u, u)), (len(r), 8, 3))
    clear = aero_clearance_m(u8, np.concatenate((r, -r), axis=1)) >= problem.clearance_min_m
    best = np.where(clear[:, None], score, -np.inf).max()
    assert res.optimum_metrics.m_min_weighted == pytest.approx(best, rel=1e-9)
    assert res.flyable_metrics.m_min_weighted <= best + 1e-12


def test_direction_step_finds_the_table_directions():
    """Step 1 (a 0.5 deg grid or a 5 deg one, refined) lands on Table 2.1's directions (to their two printed digits)."""
    for step in (0.5, 5.0):
        d = search_directions(DesignProblem(), SearchGrid(direction_step_deg=step))
        assert np.allclose(d.directions, TABLE.directions[:4], atol=0.01)
        assert np.allclose(np.round(d.directions[0], 2), [0.68, 0.28, 0.68])
        assert d.f_min_weighted >= evaluate(TABLE).f_min_weighted


def _grid_only(grid: SearchGrid) -> SearchGrid:
    return replace(grid, refine_directions=False)


@pytest.mark.parametrize("weight", [(1.0, 0.4, 1.0), (1.0, 1.0, 1.0), (0.5, 1.0, 1.0), (0.3, 0.3, 1.0), (0.9, 0.2, 0.5)])
@pytest.mark.parametrize("step", [1.0, 7.5])
def test_refinement_never_lowers_the_objective_and_ends_on_a_local_maximum(weight, step):
    problem = DesignProblem(force_weight=weight, mass_kg=0.5)
    grid = SearchGrid(direction_step_deg=step, direction_tie_tolerance=0.0)
    coarse, fine = search_directions(problem, _grid_only(grid)), search_directions(problem, grid)
    assert fine.grid_f_min_weighted == coarse.f_min_weighted
    assert fine.f_min_weighted_best >= coarse.f_min_weighted
    assert fine.f_min_weighted == pytest.approx(fine.f_min_weighted_best, rel=1e-12)
    # no point of a dense patch around the refined optimum beats it (the grid step does not matter)
    a, e = np.meshgrid(fine.azimuth_deg + np.linspace(-0.05, 0.05, 41), fine.elevation_deg + np.linspace(-0.05, 0.05, 41))
    ok = (a >= 0) & (a <= 90) & (e >= 0) & (e <= 90)
    patch = force_min_weighted(mirror_directions(np.deg2rad(a[ok]), np.deg2rad(e[ok])), weight)
    assert fine.f_min_weighted >= patch.max() - 1e-9
    # the secondary criterion: within 0.1 % of that F_min^W, never a smaller F_min, never below m g
    tie = search_directions(problem, replace(grid, direction_tie_tolerance=1e-3))
    assert tie.f_min_weighted_best == pytest.approx(fine.f_min_weighted, rel=1e-9)
    assert tie.f_min_weighted >= 0.999 * tie.f_min_weighted_best and tie.f_min_weighted >= problem.weight_lambda
    assert tie.f_min >= fine.f_min - 1e-12


def test_the_secondary_criterion_takes_the_largest_f_min_in_the_window():
    d = search_directions(DesignProblem(), SearchGrid(direction_step_deg=3.0))
    level = (1 - d.tie_tolerance) * d.f_min_weighted_best
    a, e = np.meshgrid(d.azimuth_deg + np.linspace(-0.3, 0.3, 61), d.elevation_deg + np.linspace(-0.3, 0.3, 61))
    u = mirror_directions(np.deg2rad(a), np.deg2rad(e))
    in_window = force_min_weighted(u, (1.0, 0.4, 1.0)) >= level
    assert in_window.any() and d.refined
    assert d.f_min >= force_min(u)[in_window].max() - 1e-9
    again = search_directions(DesignProblem(), SearchGrid(direction_step_deg=3.0))  # deterministic
    assert np.array_equal(again.directions, d.directions) and again.f_min == d.f_min


def test_search_reaches_the_thesis_values(tiny_search):
    """Table 2.1: F_min 2.04, F_min^xz 3.85, M_min 0.894 (two printed digits), with a tiny grid thanks to the refinement.

    F_min^xz reaches 3.8452 (prints as 3.85, 0.12 % under 3.85 itself): in the mirror family no
    direction set has both F_min >= 2.04 and F_min^xz >= 3.85 (the patch below, around the optimum).
    """
    opt, fly = tiny_search.optimum_metrics, tiny_search.flyable_metrics
    assert opt.feasible and opt.f_min >= 2.04 and opt.m_min >= 0.894 and opt.d_aero_m >= 0.125
    assert opt.f_min_xz >= 3.845 and round(opt.f_min_xz, 2) == 3.85
    assert round(opt.f_min, 2) == 2.04
    assert fly.null_structure and fly.m_min >= (1 - 0.036) * 0.894 - 0.005  # the thesis loses 3.6 % to (2.11)
    a, e = np.meshgrid(np.arange(18.0, 27.0, 0.02), np.arange(40.0, 46.0, 0.02))
    u = mirror_directions(np.deg2rad(a), np.deg2rad(e))
    assert not np.any((force_min(u) >= 2.04) & (force_min_xz(u) >= 3.85))


def test_mirror_family_has_the_force_null_structure():
    u = mirror_directions(np.deg2rad(31.0), np.deg2rad(12.0))
    assert np.allclose(u[0] - u[1] - u[2] + u[3], 0.0)


def test_an_impossible_weight_is_refused():
    with pytest.raises(ValueError, match="F_min\\^W >= m g"):
        search(DesignProblem(mass_kg=20.0), TINY)


# --- the [rotors.geometry] table ---------------------------------------------------------------


def test_without_the_table_every_config_flies_table_2_1_bit_identically():
    vs = build(VehicleSetup, {"name": "x"}, file="t")
    g, ref = vs.geometry(), RotorGeometry.odar()
    for name in ("directions", "positions_m", "spin"):
        assert np.array_equal(getattr(g, name), getattr(ref, name))
    assert "geometry" not in tomllib.loads(dump_toml(vs))["rotors"]


def test_geometry_config_round_trips(tiny_search):
    cfg = RotorGeometryConfig.from_geometry(tiny_search.flyable, source="test")
    back = build(RotorParams, tomllib.loads(dump_toml(RotorParams(geometry=cfg))), file="t")
    assert back.geometry == cfg
    g = cfg.to_geometry(0.02)
    assert np.allclose(g.mapping_matrix(), tiny_search.flyable.mapping_matrix(), atol=1e-15)


def test_search_output_loads_in_the_firmware_and_sitl_configs(tmp_path):
    out = tmp_path / "run"
    argv = ["search", "--quiet", "--direction-step-deg", "3", "--x-count", "2", "--radius-count", "1",
            "--angle-step-deg", "45", "--scenario", SCENARIO, "--out", str(out)]
    assert design_main(argv) == 0
    design = tomllib.loads((out / "design.toml").read_text())
    # firmware config: a vehicle file with that [rotors] table
    vs = build(VehicleSetup, {"name": "designed", "rotors": design["rotors"]}, file="design.toml")
    summary = json.loads((out / "design.json").read_text())
    step1 = summary["directions_step"]
    assert step1["refined"] and step1["F_min_W_best"] >= step1["grid_F_min_W"] and step1["tie_tolerance"] == 1e-3
    assert np.allclose(vs.geometry().positions_m[:4], summary["flyable_optimum"]["positions_m"])
    # SITL scenario written by the search
    sc = load_scenario(out / "scenario.toml")
    assert np.array_equal(sc.geometry().mapping_matrix(), vs.geometry().mapping_matrix())
    assert sc.firmware_for(0) is not None  # the allocator accepts the geometry
    # fleet mode writes the vehicle's part (link.toml) and the vehicle process loads it back
    part = sc.vehicle_setup()
    assert build(VehicleSetup, tomllib.loads(dump_toml(part)), file="link.toml") == part
    # evaluate reads the design file back
    assert design_main(["evaluate", "--config", str(out / "design.toml"), "--json", str(tmp_path / "m.json")]) == 0
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["M_min"] == pytest.approx(summary["flyable_optimum"]["metrics"]["M_min"], rel=1e-12)
    assert (out / "volumes.png").stat().st_size > 0


def _vehicle(geometry: dict, **skeleton):
    data = {"name": "x", "rotors": {"geometry": geometry}}
    if skeleton:
        data["skeleton"] = skeleton
    return build(VehicleSetup, data, file="bad.toml")


GOOD = {k: v for k, v in to_dict(RotorGeometryConfig.from_geometry(RotorGeometry.odar())).items() if k != "source"}


@pytest.mark.parametrize(
    "change, key, words",
    [
        ({"directions": [[0.5, 0.0, 0.0], *GOOD["directions"][1:]]}, "rotors.geometry.directions", "rotor 1 has norm"),
        ({"spin": [1, -1, 0, 1]}, "rotors.geometry.spin", "+1 or -1"),
        ({"positions_m": GOOD["positions_m"][:3]}, "rotors.geometry.positions_m", "4 arrays of 3"),
        ({"spin": [1, -1, -1, -1]}, "rotors", "null structure (2.11)"),
        ({"positions_m": [[0.4, -0.17, 0.17], [0.4, 0.17, 0.17], [0.4, -0.17, -0.17], [0.4, 0.17, -0.10]]},
         "rotors", "null structure"),
        ({"colour": "red"}, "rotors.geometry.colour", "unknown key"),
    ],
)
def test_bad_geometry_tables_are_refused_with_the_key_and_reason(change, key, words):
    with pytest.raises(ConfigError) as err:
        _vehicle({**GOOD, **change})
    assert err.value.key == key and words in err.value.reason


def test_a_geometry_beyond_the_link_tips_is_refused():
    wide = {**GOOD, "positions_m": [[0.45, y, z] for _, y, z in GOOD["positions_m"]]}
    assert _vehicle(wide).geometry().positions_m[0, 0] == 0.45  # fits the default 1 m link
    with pytest.raises(ConfigError, match="beyond the link tips"):
        _vehicle(wide, link_length_m=0.85)


def test_a_geometry_off_the_principal_axes_is_refused():
    # shifting r_j along u_j keeps t_j = r_j x u_j, hence (2.11), but tilts the principal axes
    g = RotorGeometry.odar()
    r = g.positions_m[:4] + 0.05 * g.directions[:4] * np.array([[1.0], [0.0], [0.0], [0.0]])
    cfg = RotorGeometryConfig.from_geometry(RotorGeometry.from_pairs(g.directions[:4], r, g.spin[:4]))
    geom = RotorGeometry.from_pairs(g.directions[:4], r, g.spin[:4])
    assert geom.has_null_structure() and geom.rotor_inertia_offdiag_m2() > 1e-6
    with pytest.raises(ConfigError, match="principal body axes"):
        _vehicle(to_dict(cfg))


@pytest.mark.parametrize(
    "design, key",
    [
        ({"force_weight": [1.0, 0.0, 1.0]}, "design.force_weight"),
        ({"radius_max_m": -0.1}, "design.radius_max_m"),
        ({"flow": {"radius_at_end_m": 0.2}}, "design.flow.radius_at_end_m"),
        ({"clearence_min_m": 0.1}, "design.clearence_min_m"),
    ],
)
def test_bad_design_tables_are_refused(tmp_path, design, key, capsys):
    path = tmp_path / "d.toml"
    path.write_text(dump_toml({"design": design}))
    assert design_main(["evaluate", "--config", str(path)]) == 2
    assert f"{key}:" in capsys.readouterr().err


@pytest.mark.parametrize("option, value, field", [("--angle-step-deg", "7", "angle_step_deg"),
                                                  ("--tie-tolerance", "0.5", "direction_tie_tolerance"),
                                                  ("--tie-tolerance", "nan", "direction_tie_tolerance")])
def test_bad_grid_options_are_refused(capsys, option, value, field):
    assert design_main(["search", option, value, "--quiet"]) == 2
    assert field in capsys.readouterr().err


def test_evaluate_prints_the_acceptance_keys(capsys):
    assert design_main(["evaluate"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert {"F_min", "F_min_xz", "M_min", "d_aero_m"} <= set(out)
    assert out["F_min"] == pytest.approx(2.04, rel=0.02) and out["d_aero_m"] >= 0.12


def test_a_wider_flow_volume_lowers_the_clearance():
    g = RotorGeometry.odar()
    wide = replace(FlowVolume(), radius_at_rotor_m=0.2, radius_at_end_m=0.15)
    assert float(aero_clearance_m(g.directions, g.positions_m, wide)) < float(
        aero_clearance_m(g.directions, g.positions_m, FlowVolume()))
