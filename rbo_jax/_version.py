"""The version of rbo_jax: the one place it is written (pyproject.toml reads it, hatch's
``[tool.hatch.version]``)."""

__version__ = "0.1.0"
