"""The layers run one way: companion <- link_firmware_sim <- sitl (docs/architecture.md), and the
compiled kernels are leaves: a module in a ``kernels`` folder imports only the standard library,
numpy, numba (with its llvmlite) and other kernel modules.

Every import statement of every module is read from its source (module level or inside a
function, absolute or relative), so an import added anywhere fails here.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from ..paths import ROOT

#: the kernels compiled (or loaded) before a vehicle here runs against a deadline
pytestmark = pytest.mark.usefixtures("compiled_kernels")

#: package -> the top-level packages of this repo it must never import
FORBIDDEN = {
    "companion": {"link_firmware_sim", "sitl"},
    "link_firmware_sim": {"sitl"},
}
#: third-party packages the onboard companion must not need (simulator, plotting, vision)
ONBOARD_ABSENT = ("mujoco", "matplotlib", "cv2")


def imported_modules(path: Path, package_root: Path) -> list[tuple[int, str]]:
    """``(line, dotted module)`` of every import in ``path``; relative imports resolved."""
    tree = ast.parse(path.read_text(), filename=str(path))
    module_parts = list(path.relative_to(package_root).with_suffix("").parts)
    if module_parts[-1] == "__init__":
        module_parts = module_parts[:-1]
        here = module_parts
    else:
        here = module_parts[:-1]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = here[: len(here) - (node.level - 1)] if node.level > 1 else here
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module
            out.append((node.lineno, name))
    return out


def violations(package: str, forbidden: set[str]) -> list[str]:
    bad = []
    for path in sorted((ROOT / package).rglob("*.py")):
        for line, name in imported_modules(path, ROOT):
            if name.split(".")[0] in forbidden:
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {name}")
    return bad


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_no_import_runs_upward(package):
    assert violations(package, FORBIDDEN[package]) == []


#: what a kernel module may import besides the standard library and other kernel modules
KERNEL_ALLOWED = {"numpy", "numba", "llvmlite"}
PACKAGES = ("companion", "link_firmware_sim", "sitl")


def kernel_violations(root: Path = ROOT) -> list[str]:
    """Imports of modules in a ``kernels`` folder that are not the standard library, numpy, numba
    (llvmlite) or another kernel module."""
    bad = []
    for package in PACKAGES:
        for path in sorted((root / package).rglob("kernels/**/*.py")):
            for line, name in imported_modules(path, root):
                top = name.split(".")[0]
                if top in sys.stdlib_module_names or top in KERNEL_ALLOWED or "kernels" in name.split(".")[1:]:
                    continue
                bad.append(f"{path.relative_to(root)}:{line} imports {name}")
    return bad


def test_kernels_import_only_kernels():
    assert kernel_violations() == []


#: the most arguments a compiled kernel takes: its state is
#: grouped into a few arrays (named slots: link_firmware_sim/kernels/layouts.py) and tuples
KERNEL_MAX_ARGS = 10


def test_no_kernel_takes_more_than_ten_arguments():
    wide = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("kernels/*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if (isinstance(node, ast.FunctionDef) and len(node.args.args) > KERNEL_MAX_ARGS
                        and any(isinstance(d, ast.Name) and d.id == "jit" for d in node.decorator_list)):
                    wide.append(f"{path.relative_to(ROOT)}::{node.name} takes {len(node.args.args)}")
    assert wide == []


def test_the_kernel_check_sees_a_kernel_that_imports_its_caller(tmp_path):
    kernels = tmp_path / "link_firmware_sim" / "kernels"
    kernels.mkdir(parents=True)
    (kernels / "k.py").write_text("import math\nimport numpy as np\nfrom companion.kernels.jit import jit\n"
                                  "from . import layouts\nfrom ..firmware import LinkFirmware\n")
    assert kernel_violations(tmp_path) == ["link_firmware_sim/kernels/k.py:5 imports link_firmware_sim.firmware"]


def test_the_check_sees_relative_and_function_level_imports(tmp_path):
    pkg = tmp_path / "companion" / "sub"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "m.py").write_text("def f():\n    from ...sitl import runner\n    import link_firmware_sim.ekf\n")
    found = imported_modules(pkg / "m.py", tmp_path)
    assert (2, "sitl") in found and (3, "link_firmware_sim.ekf") in found


BLOCKER = """
import importlib.abc, sys
BLOCKED = set(sys.argv[1].split(','))
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in BLOCKED:
            raise ImportError('blocked: ' + name)
sys.meta_path.insert(0, Block())
"""


def run_blocked(code: str, blocked) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", BLOCKER + code, ",".join(blocked)], capture_output=True, text=True,
                          cwd=ROOT)


def test_the_onboard_daemon_imports_without_simulator_plotting_vision_or_zenoh():
    code = ("import companion.daemon, companion.__main__, companion.engine, companion.trajectory\n"
            "assert not any(m.split('.')[0] in ('sitl', 'link_firmware_sim') for m in sys.modules), sorted(sys.modules)\n"
            "print('ok')")
    proc = run_blocked(code, ONBOARD_ABSENT + ("zenoh",))
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "ok"


def test_the_onboard_feedforward_runs_without_numba():
    """numba is the simulator's (the sim extra): without it the companion's compiled kernels are off
    and the feed-forward's numpy specification runs."""
    code = ("from companion.kernels import jit\n"
            "from companion.skeleton.body import SkeletonConfig\n"
            "from companion.skeleton.dynamics import ChainModel\n"
            "import numpy as np\n"
            "assert not jit.ENABLED\n"
            "m = ChainModel(SkeletonConfig(n_links=3))\n"
            "d = m.solve(np.zeros((3, 3)), np.repeat(np.eye(3)[None], 3, axis=0), *np.zeros((4, 3, 3)))\n"
            "assert abs(d.rotor_wrench_w[:, 2].sum() - 3 * m.inertia.mass_kg * 9.80665) < 1e-6, d.rotor_wrench_w\n"
            "assert 'numba' not in sys.modules\n"
            "print('ok')")
    proc = run_blocked(code, ONBOARD_ABSENT + ("zenoh", "numba"))
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "ok"


def test_a_vehicle_and_a_daemon_start_without_scipys_optimizer_or_lapack():
    """scipy.optimize (the inverse model's training) and scipy.linalg (the SCKF's banded path for
    long chains) load where they run: a vehicle or a companion that reads its setup does not pay
    their start-up (0.16 s each) and memory (22 and 26 MB), nor does a Raspberry Pi."""
    code = ("import link_firmware_sim.__main__, link_firmware_sim.vehicle.core, companion.__main__, companion.daemon\n"
            "from companion.config import CompanionSetup\n"
            "loaded = [m for m in ('scipy.optimize', 'scipy.linalg', 'scipy.stats') if m in sys.modules]\n"
            "assert not loaded, loaded\n"
            "print('ok')")
    proc = run_blocked(code, ONBOARD_ABSENT)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "ok"


def test_the_simulator_loads_matplotlib_only_to_write_plots():
    """``sitl fly`` and ``sitl launch`` import matplotlib after the flight, when they write its
    plots (not with ``--no-plots``): the harness flies without it (0.3 s of start-up, 28 MB)."""
    code = ("import sitl.__main__, sitl.fleet.launcher, sitl.scenarios.chain.flight, sitl.runner\n"
            "assert 'matplotlib' not in sys.modules\n"
            "print('ok')")
    proc = run_blocked(code, ("matplotlib",))
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "ok"


def test_the_blocker_really_blocks():
    proc = run_blocked("import matplotlib", ONBOARD_ABSENT)
    assert proc.returncode != 0 and "blocked: matplotlib" in proc.stderr
