import mujoco
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.estimation.so3 import quat_to_rotmat
from companion.skeleton.body import SkeletonConfig, link_inertia
from companion.skeleton.rotors import RotorGeometry, RotorParams
from link_firmware_sim.allocation import Allocator
from sitl.plant.model import SkeletonModel, rotor_controls
from sitl.plant.start import StartPose


def _model(n=3, **kw):
    cfg = SkeletonConfig(n_links=n, **kw)
    return SkeletonModel(cfg, RotorGeometry.odar(), RotorParams())


def test_elements_are_found_by_name():
    m = _model(3)
    for i in range(1, 4):
        assert m.model.body(f"link{i}").id >= 0
        for k in range(1, 9):
            assert m.model.actuator(f"link{i}_rotor{k}").id >= 0
            assert m.model.site(f"link{i}_rotor{k}").id >= 0
        for s in ("acc", "gyro", "pos", "quat", "linvel"):
            assert m.model.sensor(f"link{i}_{s}").id >= 0
    assert m.model.joint("link1_root").id >= 0
    assert m.model.joint("joint1_2").id >= 0 and m.model.joint("joint2_3").id >= 0
    assert m.actuator_ids.shape == (3, 8)


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 4), offset=st.integers(0, 5), order=st.sampled_from(["in order", "links swapped",
                                                                            "rotors reversed", "shuffled"]),
       seed=st.integers(0, 2**16))
def test_rotor_controls_write_each_thrust_to_its_actuator(n, offset, order, seed):
    """``ctrl[rotor_controls(ids)] = thrust.reshape(-1)`` puts each rotor's thrust where the gather
    ``ctrl[ids] = thrust`` does, for actuators in link and rotor order (a slice) or in any other."""
    rng = np.random.default_rng(seed)
    ids = offset + np.arange(8 * n).reshape(n, 8)
    if order == "links swapped":
        ids = ids[::-1].copy()
    elif order == "rotors reversed":
        ids = ids[:, ::-1].copy()
    elif order == "shuffled":
        ids = rng.permutation(ids.reshape(-1)).reshape(n, 8)
    thrust = rng.uniform(0.0, 8.0, (n, 8))
    gathered, written = np.full(offset + 8 * n + 2, -1.0), np.full(offset + 8 * n + 2, -1.0)
    gathered[ids] = thrust
    where = rotor_controls(ids)
    written[where] = thrust.reshape(-1)
    np.testing.assert_array_equal(written, gathered)
    if order == "in order" or (order == "links swapped" and n == 1):
        assert isinstance(where, slice)
    elif order != "shuffled":  # (a shuffle may leave them in order)
        assert not isinstance(where, slice)


def test_the_models_actuators_lie_in_link_and_rotor_order():
    """The skeleton's rotors are written with one slice (no gather) on every chain length."""
    for n in (1, 3, 7):
        assert isinstance(_model(n)._ctrl, slice)


def test_three_link_tips_coincide_while_flying_around():
    m = _model(3)
    m.reset(StartPose(center_w_m=(0.0, 0.0, 3.0), on_ground=False))
    allocator = Allocator(RotorGeometry.odar())
    pitch_up = allocator.allocate(np.array([0.0, 0.0, 17.0, 0.0, 1.5, 0.5])).command_n
    pitch_down = allocator.allocate(np.array([0.0, 0.0, 17.0, 0.0, -1.5, -0.5])).command_n
    hover = allocator.allocate(np.array([0.0, 0.0, 17.0, 0.0, 0.0, 0.0])).command_n
    thrust = np.stack((pitch_up, hover, pitch_down))
    rng = np.random.default_rng(0)
    worst = 0.0
    for k in range(1500):
        m.begin_step()
        left, right = m.tips()
        worst = max(worst, np.abs(right[:-1] - left[1:]).max())
        m.end_step(thrust + rng.normal(scale=0.5, size=(3, 8)))
    assert worst < 1e-9
    # and the joints really moved
    left, right = m.tips()
    axes = quat_to_rotmat(m.truth().q_wxyz)[:, :, 0]
    assert np.degrees(np.arccos(np.clip(axes[0] @ axes[1], -1, 1))) > 5.0


def test_rotor_actuator_wrench_equals_the_mapping_matrix():
    """MuJoCo's motor gear [0 0 1 0 0 gamma sigma] reproduces B = [u; r x u + gamma sigma u] (eq. 2.1)."""
    geometry = RotorGeometry.odar()
    cfg = SkeletonConfig(n_links=1)
    m = SkeletonModel(cfg, geometry, RotorParams())
    m.model.opt.gravity[:] = 0.0
    inertia = link_inertia(cfg, geometry)
    B = geometry.mapping_matrix()
    for k in range(8):
        m.reset(StartPose(center_w_m=(0.0, 0.0, 5.0), on_ground=False))
        thrust = np.zeros((1, 8))
        thrust[0, k] = 2.0
        m.data.ctrl[m.actuator_ids] = thrust
        mujoco.mj_forward(m.model, m.data)
        root = m.model.joint("link1_root").dofadr[0]
        acc = m.data.qacc[root : root + 6]  # free joint: world linear, body angular
        np.testing.assert_allclose(acc[:3] * inertia.mass_kg, 2.0 * B[:3, k], atol=1e-9)
        np.testing.assert_allclose(acc[3:] * np.array(inertia.inertia_kgm2), 2.0 * B[3:, k], atol=1e-9)


def test_link_inertia_is_physical():
    cfg = SkeletonConfig(n_links=1, link_mass_kg=1.8)
    I = np.array(link_inertia(cfg, RotorGeometry.odar()).inertia_kgm2)
    assert np.all(I > 0) and I[1] > I[0] and I[2] > I[0]  # a bar: roll inertia smallest
    assert I[0] + I[1] >= I[2] - 1e-12  # triangle inequality


def test_ground_start_rests_on_the_plane():
    m = _model(3)
    m.reset(StartPose(center_w_m=(1.0, 2.0, 0.0), on_ground=True))
    for _ in range(500):
        m.begin_step()
        m.end_step(np.zeros((3, 8)))
    m.begin_step()
    truth = m.truth()
    np.testing.assert_allclose(truth.p_w_m[:, 2], m.cfg.bar_radius_m, atol=5e-3)
    # accelerometer at rest reads +g (specific force, contacts included)
    np.testing.assert_allclose(truth.specific_force_b_m_s2[:, 2], 9.80665, atol=0.05)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"n_links": 0}, "n_links"),
        ({"link_mass_kg": -1.0}, "link_mass_kg"),
        ({"rotor_x_scale": 2.0}, "rotor_x_scale"),
        ({"rotor_mass_fraction": 0.8, "bar_mass_fraction": 0.5}, "rotor_mass_fraction"),
        ({"joint_limit_deg": 0.0}, "joint_limit_deg"),
    ],
)
def test_skeleton_config_is_validated(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SkeletonConfig(**kwargs)
