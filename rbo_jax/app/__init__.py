"""The application layer: the ``rbo-jax`` command line, TOML sweep configurations, the model
description :class:`~rbo_jax.app.spec.ModelSpec` and ``rbo-jax reproduce``. It only composes
library calls: no physics, no loops, no formats of its own."""
