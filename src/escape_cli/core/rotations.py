"""Rotation matrices: uniform random rotations, the paper's test protocol, axis-angle."""

from __future__ import annotations

import numpy as np

from escape_cli.core.checks import as_vector
from escape_cli.core.params import as_number
from escape_cli.errors import PointCloudError

__all__ = [
    "as_generator",
    "random_rotation",
    "paper_rotation",
    "rotation_about_axis",
    "is_rotation",
]


def as_generator(rng: np.random.Generator | int | None) -> np.random.Generator:
    """Return `rng` itself if it is a Generator, else a new one seeded with it.

    Parameters
    ----------
    rng : numpy.random.Generator or int or None
        ``None`` gives fresh OS entropy (not reproducible).
    """
    if isinstance(rng, np.random.Generator):
        return rng
    return np.random.default_rng(rng)


def random_rotation(rng: np.random.Generator | int | None = None) -> np.ndarray:
    """A rotation drawn uniformly (Haar measure) from SO(3).

    A unit quaternion with i.i.d. Gaussian components normalised to length one is
    uniform on the 3-sphere, and the quaternion-to-matrix map carries that to the
    uniform distribution on SO(3).

    Parameters
    ----------
    rng : numpy.random.Generator or int or None
        Seed or generator; the same seed gives the same rotation.

    Returns
    -------
    rotation : (3, 3) float64
        Orthonormal, determinant +1.
    """
    gen = as_generator(rng)
    q = gen.standard_normal(4)
    norm = np.linalg.norm(q)
    while norm < 1e-8:  # probability ~0; keeps the division safe
        q = gen.standard_normal(4)
        norm = np.linalg.norm(q)
    w, x, y, z = q / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ],
        dtype=np.float64,
    )


def rotation_about_axis(axis, angle: float) -> np.ndarray:
    """The right-handed rotation by `angle` radians about `axis` (Rodrigues' formula).

    R = I + sin(angle) [u]x + (1 - cos(angle)) [u]x^2 with u = axis / ||axis||.

    Parameters
    ----------
    axis : (3,) float
        Any non-zero vector; it is normalised.
    angle : float
        Radians; positive turns counter-clockwise looking down the axis.

    Returns
    -------
    rotation : (3, 3) float64
    """
    u = as_vector(axis, "the rotation axis", 3)
    n = np.linalg.norm(u)
    if n == 0.0:
        raise PointCloudError("the rotation axis must be non-zero")
    angle = as_number(angle, "the rotation angle")
    ux, uy, uz = u / n
    k = np.array([[0.0, -uz, uy], [uz, 0.0, -ux], [-uy, ux, 0.0]])  # cross-product matrix
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


def paper_rotation(rng: np.random.Generator | int | None = None) -> np.ndarray:
    """A rotation drawn as in the paper's rotated-PCN protocol (section 4.2).

    Three independent angles alpha, beta, gamma uniform in [0, 180] degrees about the
    x, y and z axes, applied together as

        R = Rz(gamma) @ Ry(beta) @ Rx(alpha)

    i.e. a column vector is turned about x first, then y, then z (fixed axes); the
    same as ``scipy.spatial.transform.Rotation.from_euler("xyz", [alpha, beta, gamma])``.
    The paper does not state the order; this is the common (extrinsic "xyz") one.
    This is *not* uniform on SO(3); use `random_rotation` for that.

    Parameters
    ----------
    rng : numpy.random.Generator or int or None
        Seed or generator; the same seed gives the same rotation.

    Returns
    -------
    rotation : (3, 3) float64
    """
    gen = as_generator(rng)
    alpha, beta, gamma = np.deg2rad(gen.uniform(0.0, 180.0, size=3))
    rx = rotation_about_axis((1.0, 0.0, 0.0), alpha)
    ry = rotation_about_axis((0.0, 1.0, 0.0), beta)
    rz = rotation_about_axis((0.0, 0.0, 1.0), gamma)
    return rz @ ry @ rx


def is_rotation(matrix, atol: float = 1e-9) -> bool:
    """True when `matrix` is (3, 3), orthonormal and has determinant +1 within `atol`."""
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (3, 3) or not np.all(np.isfinite(m)):
        return False
    return bool(
        np.allclose(m.T @ m, np.eye(3), atol=atol) and abs(np.linalg.det(m) - 1.0) <= atol
    )
