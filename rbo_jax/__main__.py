"""``python -m rbo_jax``: the ``rbo-jax`` command (:mod:`rbo_jax.app.cli`), for environments
where the console script is not on ``PATH``."""

from rbo_jax.app.cli import run

if __name__ == "__main__":
    run()
