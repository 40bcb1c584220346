"""The companion's compiled kernels (numba), and the one jit switch and SO(3) kernels of the project.

Every module here is a leaf: it imports the standard library, numpy, numba and other kernel
modules only, never the code that calls it (``tests/integration/test_layers.py`` checks). Each kernel computes
what a readable numpy function (its specification, named in the kernel's docstring) computes, with
plain loops over scalars; ``tests/unit/test_fast_paths.py`` compares the two.

* :mod:`.jit`: :data:`~.jit.ENABLED`, :func:`~.jit.jit` and :func:`~.jit.as_kernel_array`, the one
  switch of every kernel in the project (``SKELETON_JIT=0``, or no numba: the specifications run);
* :mod:`.so3`: the scalar quaternion and rotation kernels the others share;
* :mod:`.constraints`, :mod:`.sckf`, :mod:`.gate`, :mod:`.semi`: the chain constraint (eq. 3, 4),
  Alg. 1, the joint gate and the semi-decentralised group terms;
* :mod:`.align`: the step's time alignment of the link states and its corrections' attitudes;
* :mod:`.dynamics`: the chain's inverse dynamics (the feed-forward);
* :mod:`.trajectory`: a bending chain's targets;
* :mod:`.cpg`: the CPG motion generator's step (the CPG, the expected physics, the link targets);
* :mod:`.warm`: compiles (or loads from numba's cache) every kernel of this package.
"""
