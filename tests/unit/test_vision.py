"""The companion's vision measurement (companion/vision): geometry, ArUco detection, PnP, ambiguity,
covariance, on synthetic images (a cv2-drawn marker warped to a known pose). No rendering."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.estimation.so3 import quat_from_rotvec, quat_to_rotmat
from companion.vision.config import PNP_METHOD_NAMES, DetectorConfig, PipelineConfig
from companion.vision.dictionaries import ARUCO_DICTIONARY_IDS
from companion.vision.frame import CameraFrame, CameraFrameHeader
from companion.vision.geometry import (POS, ROT, CameraIntrinsics, frame_from_axes, geodesic_angle_rad, intrinsics_jacobian,
                                       project_points, projection_jacobian, transform_points, translation_error_m)
from companion.vision.markers import marker_image, marker_object_points
from companion.vision.pnp import MarkerPipeline, measure_markers, resolve_ambiguity

INTR = CameraIntrinsics.from_fov(640, 480, 60.0)
vec3 = st.tuples(*[st.floats(-1.0, 1.0)] * 3).map(np.array)


def rot(rv) -> np.ndarray:
    return quat_to_rotmat(quat_from_rotvec(np.asarray(rv, dtype=float)))


def synthetic_image(R_cm, t_cm, length_m, intr=INTR, marker_id=5, noise=0.0, seed=0) -> np.ndarray:
    """A grey image of the marker (DICT_4X4_50) at pose (R_cm, t_cm): its texture warped by the
    plane's homography K [r1 r2 t] A (A: texture pixel -> marker plane)."""
    tex, fraction = marker_image("DICT_4X4_50", marker_id, bit_px=20)
    n = tex.shape[0]
    side = length_m / fraction
    A = np.array([[side / n, 0, -side / 2 + 0.5 * side / n], [0, -side / n, side / 2 - 0.5 * side / n], [0, 0, 1]])
    H = intr.K @ np.column_stack((R_cm[:, 0], R_cm[:, 1], t_cm)) @ A
    img = cv2.warpPerspective(tex, H, (intr.width_px, intr.height_px), flags=cv2.INTER_AREA, borderValue=150)
    if noise:
        img = np.clip(img + np.random.default_rng(seed).normal(0, noise, img.shape), 0, 255).astype(np.uint8)
    return img


def test_dictionary_table_matches_opencv():
    for name, n in ARUCO_DICTIONARY_IDS.items():
        assert cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)).bytesList.shape[0] == n, name


def test_intrinsics_from_fov():
    intr = CameraIntrinsics.from_fov(640, 480, 90.0)
    assert intr.fy_px == pytest.approx(240.0) and intr.fx_px == intr.fy_px
    assert (intr.cx_px, intr.cy_px) == (319.5, 239.5)
    # a point on the top edge of the field of view projects to the top edge of the image
    assert project_points(np.array([[0.0, -1.0, 1.0]]), intr)[0, 1] == pytest.approx(-0.5)


@pytest.mark.parametrize("kwargs", [dict(width_px=0), dict(fx_px=-1.0), dict(dist_coeffs=(0.1, 0.2, 0.3)),
                                    dict(cy_px=float("nan"))])
def test_intrinsics_rejects(kwargs):
    base = dict(width_px=640, height_px=480, fx_px=500.0, fy_px=500.0, cx_px=319.5, cy_px=239.5)
    with pytest.raises(ValueError):
        CameraIntrinsics(**{**base, **kwargs})


@pytest.mark.parametrize("z, x", [((0, 0, 1), (0, 0, 1)), ((0, 0, 1), (1, 0, 0.5)), ((0, 0, 0), (1, 0, 0))])
def test_frame_from_axes_rejects(z, x):
    with pytest.raises(ValueError):
        frame_from_axes(z, x)


@given(vec3, vec3)
def test_frame_from_axes_is_a_rotation(a, b):
    if np.linalg.norm(a) < 1e-3 or np.linalg.norm(np.cross(a, b)) < 1e-3:
        return
    x = np.cross(a, b)
    R = frame_from_axes(a, x)
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-9) and np.linalg.det(R) == pytest.approx(1.0)
    assert np.allclose(R[:, 2], a / np.linalg.norm(a))


@settings(max_examples=25, deadline=None)
@given(vec3, vec3)
def test_projection_jacobian_matches_finite_differences(rv, dt):
    R = rot(0.5 * rv)
    t = np.array([0.2, -0.1, 2.0]) + 0.3 * dt
    obj = marker_object_points(0.3)
    J = projection_jacobian(obj, R, t, INTR)
    eps = 1e-6
    num = np.zeros_like(J)
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        Rp, tp = rot(d[ROT]) @ R, t + d[POS]
        Rm, tm = rot(-d[ROT]) @ R, t - d[POS]
        num[:, k] = (project_points(transform_points(Rp, tp, obj), INTR)
                     - project_points(transform_points(Rm, tm, obj), INTR)).ravel() / (2 * eps)
    assert np.allclose(J, num, rtol=1e-5, atol=1e-4)


@given(vec3)
def test_geodesic_angle_is_the_rotation_angle(rv):
    R = rot(rv)
    Q = rot(np.array([0.3, -0.2, 0.5]))
    assert geodesic_angle_rad(R @ Q, Q) == pytest.approx(np.linalg.norm(rv) % (2 * np.pi), abs=1e-6)
    assert np.allclose(translation_error_m([1.0, 2.0, 3.0], [1.0, 1.0, 1.0]), [0.0, 1.0, 2.0])


FACING = np.diag([1.0, -1.0, -1.0])  # the marker's face towards the camera (its z against the optical axis)
POSE_R = rot([0.35, -0.25, 0.4]) @ FACING
POSE_T = np.array([0.15, -0.1, 2.0])


@pytest.mark.parametrize("method", PNP_METHOD_NAMES)
def test_pipeline_recovers_a_synthetic_marker(method):
    img = synthetic_image(POSE_R, POSE_T, 0.4, noise=1.0)
    dets, poses = measure_markers(img, INTR, PipelineConfig(marker_length_m=0.4, method=method))
    assert [d.marker_id for d in dets] == [5] and len(poses) == 1
    p = poses[0]
    # P3P solves from three corners (the fourth only chooses): about 1.2 cm here, the others under 0.5 cm
    assert np.linalg.norm(translation_error_m(p.t_cm_m, POSE_T)) < (0.02 if method == "p3p" else 0.01)
    assert np.degrees(geodesic_angle_rad(p.R_cm, POSE_R)) < 1.0
    assert p.reproj_rms_px < 1.0 and not p.ambiguous
    assert np.allclose(p.cov, p.cov.T) and np.all(np.linalg.eigvalsh(p.cov) > 0)


def test_covariance_grows_as_the_marker_shrinks_in_the_image():
    stds = []
    for z in (1.5, 3.0):
        img = synthetic_image(POSE_R, np.array([0.1, -0.1, z]), 0.4)
        (p,) = measure_markers(img, INTR, PipelineConfig(marker_length_m=0.4, method="sqpnp"))[1]
        stds.append((p.side_px, np.sqrt(p.cov[POS, POS][2, 2])))
    (side_near, std_near), (side_far, std_far) = stds
    assert side_far < 0.6 * side_near
    assert std_far > 3.0 * std_near  # range variance ~ z^4 / size: twice as far, about 4x the std


def test_the_intrinsics_jacobian_is_what_a_calibration_error_does_to_the_undistorted_corners():
    """Pixels seen through a perturbed calibration and undistorted with the nominal one move by
    ``J_k dk`` (first order), for the focal lengths, the principal point and every distortion
    coefficient."""
    nominal = CameraIntrinsics(320, 240, 210.0, 212.0, 160.5, 118.0, (-0.12, 0.04, 0.001, -0.0008, 0.01))
    rng = np.random.default_rng(1)
    pc = np.column_stack((rng.uniform(-0.5, 0.5, (12, 2)), rng.uniform(1.0, 2.0, 12)))
    J = intrinsics_jacobian(pc, nominal)
    k0 = np.array([nominal.fx_px, nominal.fy_px, nominal.cx_px, nominal.cy_px, *nominal.dist_coeffs])
    pinhole = project_points(pc, nominal)
    for j, step in enumerate([0.05, 0.05, 0.05, 0.05, 1e-5, 1e-5, 1e-6, 1e-6, 1e-5]):
        k = k0.copy()
        k[j] += step
        true = CameraIntrinsics(320, 240, *k[:4], tuple(k[4:]))
        seen, _ = cv2.projectPoints(pc, np.zeros(3), np.zeros(3), true.K, true.dist)
        undist = cv2.undistortPoints(seen, nominal.K, nominal.dist, P=nominal.K).reshape(-1, 2)
        # first order, leaving out the distortion's own slope: a few per cent near the image's edges
        expected = J[:, j] * step
        np.testing.assert_allclose((undist - pinhole).ravel(), expected, atol=0.1 * np.abs(expected).max())


def test_the_calibrations_accuracy_widens_the_pose_covariance():
    img = synthetic_image(POSE_R, np.array([0.1, -0.1, 1.5]), 0.4)
    plain = PipelineConfig(marker_length_m=0.4)
    (p0,) = measure_markers(img, INTR, plain)[1]
    (p1,) = measure_markers(img, INTR, dataclasses.replace(plain, calib_principal_std_px=2.0))[1]
    (p2,) = measure_markers(img, INTR, dataclasses.replace(plain, calib_focal_std_frac=0.01))[1]
    assert np.all(np.linalg.eigvalsh(p1.cov - p0.cov) > -1e-15) and np.all(np.linalg.eigvalsh(p2.cov - p0.cov) > -1e-15)
    # a principal point error is a common image shift: it tilts the pose by about 2 px / f
    tilt = np.sqrt(np.linalg.eigvalsh(p1.cov[ROT, ROT] - p0.cov[ROT, ROT])[-1])
    assert tilt == pytest.approx(2.0 / INTR.fx_px, rel=0.3)
    # a focal error scales the range (fx and fy independent: half of it each)
    assert np.sqrt(p2.cov[POS, POS][2, 2] - p0.cov[POS, POS][2, 2]) == pytest.approx(0.01 * 1.5 / np.sqrt(2), rel=0.2)
    with pytest.raises(ValueError, match="calib_focal_std_frac"):
        PipelineConfig(calib_focal_std_frac=-0.1)


def test_ambiguity_keeps_the_residual_winner_or_the_continuous_candidate():
    R_a, R_b = rot([0.0, 0.4, 0.0]), rot([0.0, -0.4, 0.0])
    t = np.array([0.0, 0.0, 2.0])
    clear = [(R_a, t, 0.1), (R_b, t, 1.0)]
    assert resolve_ambiguity(clear, R_b, 3.0)[:2] == (0, False)  # residuals decide
    close = [(R_a, t, 0.1), (R_b, t, 0.12)]
    assert resolve_ambiguity(close, None, 3.0)[:2] == (0, True)  # flagged, best kept
    assert resolve_ambiguity(close, rot([0.0, -0.35, 0.0]), 3.0)[:2] == (1, True)  # continuity


def test_class_and_function_agree_over_a_sequence():
    cfg = PipelineConfig(marker_length_m=0.4, method="ippe_square")
    pipe = MarkerPipeline(cfg)
    previous = {}
    for k in range(3):
        img = synthetic_image(rot([0.0, 0.05 * k, 0.02 * k]) @ POSE_R, POSE_T + [0.02 * k, 0.0, 0.1 * k], 0.4, noise=1.0, seed=k)
        a = pipe(img, INTR)
        _, b = measure_markers(img, INTR, cfg, previous=previous)
        previous = {p.marker_id: p for p in b}
        assert len(a) == len(b) == 1
        assert np.allclose(a[0].t_cm_m, b[0].t_cm_m) and np.allclose(a[0].R_cm, b[0].R_cm)
        assert np.allclose(a[0].cov, b[0].cov)


def test_distorted_corners_are_undistorted():
    intr = CameraIntrinsics.from_fov(640, 480, 60.0, dist_coeffs=(-0.2, 0.05, 0.0, 0.0, 0.0))
    pinhole = synthetic_image(POSE_R, POSE_T + [0.4, 0.3, 0.0], 0.4)  # off-centre: distortion moves it
    u, v = np.meshgrid(np.arange(640.0), np.arange(480.0))
    und = cv2.undistortPoints(np.stack((u.ravel(), v.ravel()), 1).reshape(-1, 1, 2), intr.K, intr.dist, P=intr.K)
    und = und.reshape(480, 640, 2).astype(np.float32)
    img = cv2.remap(pinhole, und[..., 0], und[..., 1], cv2.INTER_LINEAR, borderValue=150)
    cfg = PipelineConfig(marker_length_m=0.4, method="sqpnp")
    (p,) = measure_markers(img, intr, cfg)[1]
    assert np.linalg.norm(p.t_cm_m - (POSE_T + [0.4, 0.3, 0.0])) < 0.01
    (q,) = measure_markers(img, CameraIntrinsics.from_fov(640, 480, 60.0), cfg)[1]  # ignoring it is worse
    assert np.linalg.norm(q.t_cm_m - (POSE_T + [0.4, 0.3, 0.0])) > 2 * np.linalg.norm(p.t_cm_m - (POSE_T + [0.4, 0.3, 0.0]))


@pytest.mark.parametrize("bad", [dict(dictionary="DICT_9X9_50"), dict(refinement_window_px=0)])
def test_detector_config_rejects(bad):
    with pytest.raises(ValueError):
        DetectorConfig(**bad)


def test_frame_header_validates():
    h = dict(camera="down", vehicle=1, seq=0, t_capture_s=1.0, t_available_s=1.05, width_px=640, height_px=480,
             encoding="rgb8", intrinsics=INTR)
    frame = CameraFrame(CameraFrameHeader(**h), np.zeros((480, 640, 3), np.uint8))
    assert frame.header.latency_s == pytest.approx(0.05) and frame.header.version == 1
    for bad in (dict(version=2), dict(t_available_s=0.9), dict(width_px=320), dict(encoding="jpeg")):
        with pytest.raises(ValueError):
            CameraFrameHeader(**{**h, **bad})
    with pytest.raises(ValueError):
        CameraFrame(CameraFrameHeader(**h), np.zeros((480, 640), np.uint8))


@pytest.mark.integration
def test_vision_config_and_geometry_import_without_opencv():
    import subprocess
    import sys

    code = ("import importlib.abc, sys\n"
            "class Block(importlib.abc.MetaPathFinder):\n"
            "    def find_spec(self, name, path=None, target=None):\n"
            "        if name.split('.')[0] in ('cv2', 'mujoco'):\n"
            "            raise ImportError('blocked: ' + name)\n"
            "sys.meta_path.insert(0, Block())\n"
            "import companion.vision, companion.vision.geometry, companion.vision.frame, companion.vision.config\n"
            "import sitl.cameras.config, sitl.scenario\n"
            "try:\n"
            "    import companion.vision.pnp\n"
            "except ImportError as e:\n"
            "    print('blocked' in str(e))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "True"


def test_the_flight_log_resolves_each_cameras_ambiguity_from_that_cameras_own_last_pose():
    """Two cameras see marker 5: camera 2's ambiguous view (small, nearly fronto-parallel) is
    resolved from camera 2's previous pose of it, not from camera 1's (another pose of the same
    marker, mirrored here): the pose kept is the true one."""
    from sitl.cameras.config import MarkerMount
    from sitl.cameras.rig import CapturedFrame, FrameTruth
    from sitl.cameras.vision_log import VisionLog

    def frame(camera: int, seq: int, tilt: float, dist: float) -> CapturedFrame:
        R, t = FACING @ rot([0.0, -tilt, 0.0]), np.array([0.0, 0.0, dist])
        header = CameraFrameHeader(f"cam{camera}", camera - 1, seq, 0.1 * seq, 0.1 * seq, INTR.width_px,
                                   INTR.height_px, "mono8", INTR)
        truth = FrameTruth(np.eye(3), np.zeros(3), {5: (R, t)})  # the camera at the world's origin
        return CapturedFrame(CameraFrame(header, synthetic_image(R, t, 0.5, noise=2.0)), truth, camera - 1)

    def last_error_deg(last_camera: int) -> float:
        log = VisionLog((MarkerMount(id=5, size_m=0.5),), methods=("ippe_square",))
        for f in (frame(2, 0, 0.3, 2.0), frame(1, 1, -0.3, 2.0), frame(last_camera, 2, 0.15, 4.0)):
            log.on_frame(f)
        a = log.arrays()
        assert not a["vision_ambiguous"][:2].any() and a["vision_ambiguous"][2]  # the last view is ambiguous
        return a["vision_att_err_deg"][2]

    assert last_error_deg(2) < 3.0  # camera 2's last pose (tilted the same way) picks the true solution
    assert last_error_deg(1) > 10.0  # the same view after camera 1's opposite pose: the mirrored one


def test_the_corner_bench_measures_each_refinement_against_the_true_corners():
    """sitl.bench corners' frame consumer on synthetic frames of a known pose: every refinement
    finds the marker, its corners within a pixel of the true ones, the pose within centimetres;
    the figures are per refinement and its detection time is counted."""
    from sitl.bench.corners import REFINEMENTS, CornerLog
    from sitl.cameras.config import MarkerMount
    from sitl.cameras.rig import CapturedFrame, FrameTruth

    log = CornerLog((MarkerMount(id=5, size_m=0.4),))
    for seq, rv in enumerate(([0.35, -0.25, 0.4], [0.1, 0.3, -0.2])):
        R, t = rot(rv) @ FACING, np.array([0.15, -0.1, 2.0])
        header = CameraFrameHeader("cam1", 0, seq, 0.1 * seq, 0.1 * seq, INTR.width_px, INTR.height_px, "mono8", INTR)
        log.on_frame(CapturedFrame(CameraFrame(header, synthetic_image(R, t, 0.4, noise=1.0, seed=seq)),
                                   FrameTruth(np.eye(3), np.zeros(3), {5: (R, t)}), 0))
    m = log.metrics()
    assert list(m) == list(REFINEMENTS) and log.frames == 2
    for r in REFINEMENTS:
        assert m[r]["detections"] == 2 and m[r]["corner_rms_px"] < 1.0 and abs(m[r]["inward_bias_px"]) < 1.0
        assert m[r]["pos_rms_cm"] < 3.0 and m[r]["att_rms_deg"] < 2.0 and m[r]["detect_ms_per_frame"] > 0
    assert m["subpix"]["corner_rms_px"] < m["none"]["corner_rms_px"]  # refining moves corners towards the truth
