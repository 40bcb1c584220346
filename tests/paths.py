"""Where the tests find the repository's files."""

from pathlib import Path

#: the repository's root (the folder of pyproject.toml)
ROOT = Path(__file__).resolve().parents[1]
#: the SITL scenarios, by kind (configs/sitl/<kind>/)
SITL_CONFIGS = ROOT / "configs" / "sitl"
#: the three-link chain flown by the fleet tests
THREE_LINK = SITL_CONFIGS / "chain" / "three_link.toml"
