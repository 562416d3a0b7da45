"""A generated scene for tests, examples and benchmarks that must run without real scans: a room
corner (floor and two walls), a sphere and a capped cylinder, sampled uniformly by area, with
exact normals, optional noise, and a pair of views related by a known rigid motion."""

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike

from .._checks import to_device
from ..groups import SE3, kernels

# (kind, parameters): the floor z = 0 and walls x = -1, y = -1 over [-1, 1]^2 patches, a sphere and
# a vertical cylinder standing on the floor. Together they constrain all six degrees of freedom of
# point-to-plane ICP (planes alone would leave slides along their intersection line free).
_PARTS = (
    (
        "plane",
        (np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), 2.0, 2.0),
    ),
    (
        "plane",
        (
            np.array([-1.0, 0.0, 0.5]),
            np.array([0.0, 1.0, 0.0]),
            np.array([0.0, 0.0, 1.0]),
            2.0,
            1.0,
        ),
    ),
    (
        "plane",
        (
            np.array([0.0, -1.0, 0.5]),
            np.array([1.0, 0.0, 0.0]),
            np.array([0.0, 0.0, 1.0]),
            2.0,
            1.0,
        ),
    ),
    ("sphere", (np.array([0.35, 0.25, 0.3]), 0.3)),
    ("cylinder", (np.array([-0.45, 0.45, 0.0]), 0.2, 0.7)),
)


def _areas():
    areas = []
    for kind, p in _PARTS:
        if kind == "plane":
            areas.append(p[3] * p[4])
        elif kind == "sphere":
            areas.append(4 * np.pi * p[1] ** 2)
        else:
            areas.append(2 * np.pi * p[1] * p[2])
    return np.array(areas)


def _sample_part(rng, kind, p, count):
    if kind == "plane":
        centre, u, v, width, height = p
        a = rng.uniform(-0.5, 0.5, (count, 1)) * width
        b = rng.uniform(-0.5, 0.5, (count, 1)) * height
        normal = np.cross(u, v)
        return centre + a * u + b * v, np.broadcast_to(normal, (count, 3))
    if kind == "sphere":
        centre, radius = p
        direction = rng.normal(size=(count, 3))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        return centre + radius * direction, direction
    base, radius, height = p
    angle = rng.uniform(0, 2 * np.pi, count)
    radial = np.stack([np.cos(angle), np.sin(angle), np.zeros(count)], axis=1)
    z = rng.uniform(0, height, (count, 1)) * np.array([0.0, 0.0, 1.0])
    return base + radius * radial + z, radial


def synthetic_scene(
    n: int = 2000, *, noise: float = 0.0, seed: int = 0, dtype: DTypeLike = jnp.float64
) -> tuple[jax.Array, jax.Array]:
    """`(points, normals)`, each `(n, 3)`: the scene sampled uniformly by area (about 2 m across),
    Gaussian noise of standard deviation `noise` added along each point's normal."""
    rng = np.random.default_rng(seed)
    areas = _areas()
    counts = rng.multinomial(n, areas / areas.sum())
    points, normals = [], []
    for (kind, p), count in zip(_PARTS, counts):
        pts, nrm = _sample_part(rng, kind, p, count)
        points.append(pts)
        normals.append(nrm)
    points, normals = np.concatenate(points), np.concatenate(normals)
    points = points + noise * rng.normal(size=(n, 1)) * normals
    return to_device(points.astype(dtype)), to_device(normals.astype(dtype))


def synthetic_pair(
    n: int = 2000,
    *,
    rotation_deg: float = 10.0,
    translation: float = 0.1,
    noise: float = 0.0,
    same_samples: bool = True,
    seed: int = 0,
    dtype: DTypeLike = jnp.float64,
) -> tuple[jax.Array, jax.Array, jax.Array, SE3]:
    """Two views of the scene related by a known motion.

    **Arguments:**

    - `n`: points per view.
    - `rotation_deg`, `translation`: size of the motion (random axis and direction).
    - `noise`: standard deviation of the noise along the normals, independent in each view.
    - `same_samples`: the source is the target's own samples moved (exact recovery is possible);
      False samples it independently (as two real scans would).
    - `seed`: everything is reproducible from it.

    **Returns:** `(source, target, target_normals, T_target_source)`: `source` in its own frame,
    with `T_target_source @ source` lying on the target's surfaces.
    """
    rng = np.random.default_rng(seed + 1)
    target, target_normals = synthetic_scene(n, noise=noise, seed=seed, dtype=dtype)
    if same_samples:
        on_target = np.asarray(synthetic_scene(n, noise=0.0, seed=seed, dtype=dtype)[0])
        normals = np.asarray(target_normals)
        on_target = (
            on_target + noise * np.random.default_rng(seed + 2).normal(size=(n, 1)) * normals
        )
    else:
        on_target = np.asarray(synthetic_scene(n, noise=noise, seed=seed + 1000, dtype=dtype)[0])
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    tangent = np.concatenate([translation * direction, np.deg2rad(rotation_deg) * axis])
    T_target_source = SE3.exp(np.asarray(tangent, dtype))  # NumPy inside: nothing to compile
    params = np.asarray(T_target_source.parameters())
    rotation, translation = kernels.host_so3_as_matrix(params[:4]), params[4:]
    source = (on_target - translation) @ rotation  # T⁻¹ p = Rᵀ (p - t), on rows
    return to_device(source.astype(dtype)), target, target_normals, T_target_source
