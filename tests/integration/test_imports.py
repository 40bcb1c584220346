import subprocess
import sys

BLOCKER = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in {'pymavlink', 'zenoh', 'mujoco', 'mavsdk', 'pinocchio', 'cv2'}:
            raise ImportError('blocked: ' + name)
sys.meta_path.insert(0, Block())
"""


def _python(code: str) -> str:
    """What ``code`` printed in a fresh interpreter (which must exit 0)."""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def test_estimation_core_imports_without_wire_or_sim_packages():
    code = BLOCKER + (
        "import companion.estimation, link_firmware_sim.estimators.ekf, sitl.synthetic, sitl.bench.table2, companion.replay\n"
        "import companion.messages, companion.corrections, companion.fleetnet.codec, companion.fleetnet.leader\n"
        "import companion.fleetnet.config, companion.fleetnet.hub, companion.fleetnet.group, companion.motion.cpg\n"
        "import companion.engine, companion.config, companion.trajectory, companion.skeleton.kinematics\n"
        "import link_firmware_sim.firmware, link_firmware_sim.allocation, link_firmware_sim.controllers\n"
        "print('ok')"
    )
    assert _python(code).strip() == "ok"


def test_the_pure_core_and_its_compiled_kernels_import_without_mujoco():
    """The estimation core and every compiled kernel (numba's, as in the simulator) load without
    MuJoCo: their unit tests run without it."""
    code = BLOCKER + (
        "import numba, companion.estimation, companion.kernels.warm, link_firmware_sim.kernels.warm\n"
        "import companion.kernels.sckf, companion.kernels.so3, link_firmware_sim.kernels.tick\n"
        "import os; assert companion.kernels.warm.ENABLED or os.environ.get('SKELETON_JIT') == '0'\n"
        "print('ok')"
    )
    assert _python(code).strip() == "ok"


def test_blocker_really_blocks():
    proc = subprocess.run([sys.executable, "-c", BLOCKER + "import mujoco"], capture_output=True, text=True)
    assert proc.returncode != 0 and "blocked" in proc.stderr


def test_the_campaign_engine_loads_without_dask_and_says_how_to_get_it():
    """Dask is an extra ([campaign], in [sim]): without it the campaign modules and the benches
    over seeds still import, the serial executor runs, and a cluster is refused with the install hint."""
    code = BLOCKER.replace("'cv2'}", "'cv2', 'dask', 'distributed'}") + (
        "import sitl.campaign.grid, sitl.campaign.engine, sitl.campaign.table, sitl.campaign.summary\n"
        "import sitl.campaign.flights, sitl.campaign.cli, sitl.campaign.cluster, sitl.bench.seeds\n"
        "from sitl.campaign.cluster import connect\n"
        "try:\n"
        "    with connect(workers=1):\n"
        "        pass\n"
        "except ImportError as exc:\n"
        "    print(exc)\n"
    )
    assert "Dask distributed is missing; install it with pip install 'aerial-skeleton-stack[campaign]'" in _python(code)
