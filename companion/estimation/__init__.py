"""Pure estimation core of the companion: SO(3) helpers, chain constraints (eq. 3-4),
constraint application (Alg. 1), semi-distributed step (Alg. 2, eq. 6).

numpy/scipy only: no I/O, clocks, sockets or asyncio. Imports without pymavlink, zenoh or
mujoco.
"""

from .chain import (
    CON_DIM,
    CON_POS,
    CON_VEL,
    ERR_DIM,
    ERR_P,
    ERR_PV,
    ERR_TH,
    ERR_V,
    ChainInputError,
    check_chain,
    check_covariance_blocks,
)
from .constraints import (
    constraint_jacobian,
    constraint_jacobian_blocks,
    constraint_norm,
    constraint_residual,
    left_tip,
    right_tip,
    tip_offsets,
)
from .sckf import (
    CAParams,
    CAResult,
    constraint_apply,
    constraint_apply_dense,
    constraint_apply_structured,
)
from .semi import (
    GroupBoundary,
    Groups,
    SemiResult,
    format_groups,
    global_step,
    group_boundary,
    make_groups,
    parse_groups,
    semi_distributed_apply,
    validate_groups,
)

__all__ = [
    "CON_DIM",
    "CON_POS",
    "CON_VEL",
    "ERR_DIM",
    "ERR_P",
    "ERR_PV",
    "ERR_TH",
    "ERR_V",
    "ChainInputError",
    "check_chain",
    "check_covariance_blocks",
    "constraint_jacobian",
    "constraint_jacobian_blocks",
    "constraint_norm",
    "constraint_residual",
    "left_tip",
    "right_tip",
    "tip_offsets",
    "CAParams",
    "CAResult",
    "constraint_apply",
    "constraint_apply_dense",
    "constraint_apply_structured",
    "GroupBoundary",
    "Groups",
    "SemiResult",
    "format_groups",
    "global_step",
    "group_boundary",
    "make_groups",
    "parse_groups",
    "semi_distributed_apply",
    "validate_groups",
]
