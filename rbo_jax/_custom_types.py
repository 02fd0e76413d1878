"""Shape-annotated type aliases shared by the package (cf. diffrax ``_custom_types.py``)."""

from jaxtyping import Array, ArrayLike, Bool, Float, Real

Scalar = Float[Array, ""]
ScalarLike = Real[ArrayLike, ""]
Vector = Float[Array, "3"]
VectorLike = Real[ArrayLike, "3"]
Matrix = Float[Array, "3 3"]
MatrixLike = Real[ArrayLike, "3 3"]
BoolScalar = Bool[Array, ""]

__all__ = [
    "Scalar",
    "ScalarLike",
    "Vector",
    "VectorLike",
    "Matrix",
    "MatrixLike",
    "BoolScalar",
]
