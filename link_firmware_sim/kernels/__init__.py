"""The firmware's compiled kernels (numba): leaves that import only the standard library, numpy,
numba and other kernels (:mod:`companion.kernels`: the jit switch, the SO(3) kernels).

Each computes what a readable numpy specification computes, named in its docstring, with plain
loops over scalars; ``tests/unit/test_fast_paths.py`` compares the two, and with ``SKELETON_JIT=0`` (or
without numba) the firmware runs the specifications. At 500 Hz per link the interpreter's cost of a
few hundred scalar operations, not the arithmetic, was the simulator's limit.

* :mod:`.layouts`: the named slots of the kernels' grouped state (the EKF's parameters, eq. 1's
  controller, the allocator, the fused tick's inputs and results, the vehicle's side);
* :mod:`.ekf`: the EKF's propagation and updates (paper eq. 2);
* :mod:`.impedance`: eq. 1;
* :mod:`.allocation`: the allocation with selective mapping (thesis Prop. 1, (2.15), (2.17));
* :mod:`.tick`: the fast loop's tick in one call, and the vehicle's record tick;
* :mod:`.hil_records`: the simulator link's record layouts;
* :mod:`.mavlink_frames`: those records in MAVLink 2 frames (PX4's TCP link);
* :mod:`.libc`: ``poll``, ``recv`` and ``send`` as intrinsics;
* :mod:`.lockstep`: the vehicle's loop over its quiet ticks;
* :mod:`.warm`: compiles (or loads) them all.
"""
