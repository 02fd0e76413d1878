r"""The numerical kernels every analysis shares: one loop for iterative solves
(:mod:`._iterate`), Newton's update and its convergence test (:mod:`._newton`), one
implicit-derivative rule (:mod:`._implicit`) and the linear solvers a model's structure
asks for (:mod:`._linear`: dense, least squares, block-tridiagonal); the fits' nonlinear least
squares, iterated on the host, and their Gauss–Newton covariance (:mod:`._least_squares`).

The shape is optimistix's: its root finders, least squares and minimisers all run in one
``_iterate`` loop and get their derivatives from one ``ImplicitAdjoint``. Here equilibria,
Hopf and Bautin points, continuation correctors, periodic orbits and folds of cycles are all
steps run by :func:`iterate`, and differentiated through :func:`implicit`.
"""

from .. import _lazy

__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    {  # loaded on first use
        "._iterate": ("RUNNING", "iterate"),
        "._outcome": ("Outcome",),
        "._newton": ("converged", "newton_step", "newton_update"),
        "._implicit": ("Implicit", "implicit"),
        "._least_squares": (
            "gauss_newton_covariance",
            "levenberg_marquardt",
            "record_loss",
            "run_least_squares",
            "value_and_jacfwd",
        ),
        "._linear": (
            "AbstractLinearSolver",
            "Dense",
            "FactoredTridiagonal",
            "LeastSquares",
            "Tridiagonal",
            "TruncatedLeastSquares",
            "bordered_solve",
            "equilibrated_lstsq",
            "linear_solver",
            "tridiagonal_differences",
            "tridiagonal_factor",
            "tridiagonal_jacobian",
            "tridiagonal_matvec",
            "tridiagonal_solve",
            "tridiagonal_substitute",
        ),
    },
)
