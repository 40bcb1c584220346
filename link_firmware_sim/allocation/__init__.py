"""Control allocation of one 8-rotor ODAR link with selective mapping (thesis ch. 2, sec. 2.4).

* :mod:`.mapping`: the equations, a functional core in numpy, with the parameters and the result;
* :mod:`.allocator`: :class:`Allocator`, the stateful allocator the firmware runs, with the one
  dispatch between that specification and the kernel (:mod:`link_firmware_sim.kernels.allocation`).
"""

from .allocator import Allocator
from .mapping import (MARGIN_TOL_N, AllocationParams, AllocationResult, gradual_selective_mapping,
                      infinity_norm_allocation, pseudo_inverse, reduced_pseudo_inverse, reduced_pseudo_inverses,
                      scaled_to_limit, selective_mapping_weights, selective_modulation)

__all__ = ["MARGIN_TOL_N", "AllocationParams", "AllocationResult", "pseudo_inverse", "reduced_pseudo_inverse",
           "reduced_pseudo_inverses", "infinity_norm_allocation", "scaled_to_limit", "selective_modulation",
           "selective_mapping_weights", "gradual_selective_mapping", "Allocator"]
