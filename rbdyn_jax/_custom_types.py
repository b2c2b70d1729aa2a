"""Array type aliases used in signatures (jaxtyping), one place for the whole package."""

from jaxtyping import Array, ArrayLike, Bool, Float

Scalar = Float[Array, "*batch"]
ScalarLike = Float[ArrayLike, "*batch"]
Vector = Float[Array, "*batch 3"]
VectorLike = Float[ArrayLike, "*batch 3"]
Quaternion = Float[Array, "*batch 4"]
QuaternionLike = Float[ArrayLike, "*batch 4"]
Matrix = Float[Array, "*batch 3 3"]
MatrixLike = Float[ArrayLike, "*batch 3 3"]
Angles = Float[Array, "*batch 3"]
AnglesLike = Float[ArrayLike, "*batch 3"]
BoolArray = Bool[Array, "*batch"]

__all__ = [
    "Angles",
    "AnglesLike",
    "BoolArray",
    "Matrix",
    "MatrixLike",
    "Quaternion",
    "QuaternionLike",
    "Scalar",
    "ScalarLike",
    "Vector",
    "VectorLike",
]
