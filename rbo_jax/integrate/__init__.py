r"""What the integrators of every model share (DESIGN.md: the ``integrate`` layer).

- :mod:`.diffeq`: the one diffrax solve (term, solver, step-size controller, adjoint and events
  as diffrax has them, sampled at given times), its statuses, and how a model's compiled solve
  is called. :func:`rbo_jax.simulate` of a rigid body and its Darboux problems, a lattice's
  ``method="diffrax"`` and a rod's explicit and implicit methods go through it.
- :mod:`.dop853`: one DOP853 step exactly as SciPy takes it (shape-polymorphic: one trajectory,
  lanes of trajectories, or the bodies of one lattice) and its dense samples; the coefficients
  in :mod:`.tableau`. :func:`rbo_jax.fast_simulate` (the ensemble) and a lattice's
  ``method="dop853"`` loop over it.
- :mod:`.midpoint`: the implicit midpoint rule for a chain of bodies (a rod), its Newton
  matrices block-tridiagonal (O(N) a step): a rod's ``method="midpoint"``, the default for a
  stiff rod.

Each model keeps its own integrators and defaults (:mod:`rbo_jax.simulate`,
:mod:`rbo_jax.ensemble`, :mod:`rbo_jax.lattice`). The modules are imported one by one (none of
them here): the ensemble does not import diffrax.
"""
