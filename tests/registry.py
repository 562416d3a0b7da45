"""The one registry that drives the group tests.

Adding a group means adding one `GroupSpec` to `GROUPS`: every test in `test_groups.py`,
`test_jacobians.py`, `test_second_order.py`, `test_properties.py` and `test_errors.py` is
parametrized over it (SO2, SE2, SO3, SE3 and Sim3 are registered). `MANIFOLDS` adds the manifolds
that are not groups (S2, a `ManifoldSpec`): the properties every manifold has (`rplus` / `rminus`
round trips, their Jacobians, finite gradients, dtypes, broadcasting) run over it
(`test_properties.py`); S2's own operations are tested in `test_sim3_s2.py`. Each spec
carries NumPy reference formulas (`hat`, `vee`, the action on points) written from the conventions in
`shared/DESIGN.md`, independently of lieax, so that values and finite differences are computed on
matrices: `X ⊕ δ = X · expm(hat(δ))` and `Y ⊖ X = vee(logm(X⁻¹ Y))`.

Also here: the regimes of test points (identity, 1e-9 from it, pure translation, translation and
scale (Sim3), pure scale, ~1e-4 rad, near π, random), the edge regimes of the property suite (as
hypothesis examples), the operations checked for every group (with their matrix formulas), and
the documented tolerances (float64 finite differences, float32 accuracy).
"""

import dataclasses
from collections.abc import Callable

import jax.numpy as jnp
import numpy as np
import scipy.linalg

from lieax import S2, SE2, SE3, SE23, SO2, SO3, Sim3

# ---- NumPy reference formulas ------------------------------------------------------------------


def skew3(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def unskew3(m):
    return 0.5 * np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])


def skew2(w):
    return np.array([[0.0, -w], [w, 0.0]])


@dataclasses.dataclass(frozen=True)
class GroupSpec:
    """One group under test, with reference formulas on single (unbatched) NumPy matrices."""

    name: str
    cls: type
    rotation_index: tuple  # tangent coordinates of the rotation (the angle or ω)
    translation_index: tuple  # tangent coordinates of the translation (empty for SO groups)
    hat: Callable  # tangent (d,) -> Lie algebra matrix (n, n)
    vee: Callable  # Lie algebra matrix -> tangent
    rotation_parameters: int  # leading parameters that `normalize` rescales to unit norm
    scale_index: tuple = ()  # tangent coordinate of the log-scale σ (Sim3), empty for rigid groups
    # the group's own constructors (besides identity, exp, from_matrix, sample_uniform), called
    # with float32 or float64 arrays and Python numbers: dtype -> {name: element}
    constructors: Callable = lambda dtype: {}

    is_group = True

    def __repr__(self):
        return self.name

    def tangent(self, angle, axis, translation, log_scale) -> np.ndarray:
        """The tangent `(d,)` with rotation angle `angle` about `axis` (its first coordinate's sign
        for planar groups), the coordinates of `translation` and the log-scale."""
        xi = np.zeros(self.dim)
        axis = np.asarray(axis, dtype=float)[: len(self.rotation_index)]
        if len(self.rotation_index) == 1:
            xi[list(self.rotation_index)] = angle if axis[0] >= 0 else -angle
        else:
            xi[list(self.rotation_index)] = angle * axis / np.linalg.norm(axis)
        # the translation's coordinates, repeated where a group has more (SE23's velocity)
        xi[list(self.translation_index)] = np.resize(translation, len(self.translation_index))
        xi[list(self.scale_index)] = log_scale
        return xi

    def random_base(self, seed: int) -> np.ndarray:
        """What `base` makes a random element from: a random tangent (deterministic per seed)."""
        return random_tangents(self, 1, seed)[0]

    def base(self, array):
        """The element of `random_base`'s array: `Exp(η)`."""
        return self.cls.exp(array)

    @property
    def dim(self) -> int:
        return self.cls.tangent_dim

    @property
    def n(self) -> int:
        return self.cls.matrix_dim

    @property
    def space(self) -> int:
        return self.cls.space_dim

    @property
    def has_translation(self) -> bool:
        return len(self.translation_index) > 0

    @property
    def has_scale(self) -> bool:
        return len(self.scale_index) > 0

    def rotation_block(self, matrix):
        """The rotation in a (batch of) matrices: the linear block divided by its scale
        `det^(1/k)` for groups with a scale (so that `R Rᵀ = I` and `det R = 1` can be checked
        for every group)."""
        k = self.space
        linear = np.asarray(matrix)[..., :k, :k]
        if self.has_scale:
            linear = linear / (np.linalg.det(linear) ** (1.0 / k))[..., None, None]
        return linear

    def expm(self, xi):
        return scipy.linalg.expm(self.hat(xi))

    def logm(self, matrix):
        """`vee(logm(M))`, the principal logarithm (rotation angle below π).

        For the affine groups `M = [A, b; 0, 1]` the logarithm is taken blockwise,
        `log M = [L, φ(L)⁻¹ b; 0, 0]` with `L = logm(A)` and `φ(L) = Σ_k L^k / (k + 1)!` read off
        `expm([L, I; 0, 0])` and `L` projected on the skew-symmetric matrices: `scipy.linalg.logm`
        is ill-conditioned near angle π (condition number ~θ / sin θ ≈ 3e6 at π - 1e-6): it loses
        ~4e-10 on the translation and in the symmetric part of `L`, which finite differences with
        a 1e-7 step turn into errors of 1e-3. This form is accurate to ~1e-15 there. With a scale
        (Sim3, `A = e^σ R`), `σ = log(det A) / 3` (never from the symmetric part of `logm(A)`,
        which is the inaccurate part) and `L = σ I + skew(logm(R))`, `R = A e^(-σ)`."""
        if not self.has_translation:
            return self.vee(np.real(scipy.linalg.logm(matrix)))
        k = self.space
        sigma = np.log(np.linalg.det(matrix[:k, :k])) / k if self.has_scale else 0.0
        linear = np.real(scipy.linalg.logm(matrix[:k, :k] * np.exp(-sigma)))
        linear = 0.5 * (linear - linear.T)  # logm's symmetric part is rounding error, ~1e-10 near π
        linear = linear + sigma * np.eye(k)
        augmented = np.zeros((2 * k, 2 * k))
        augmented[:k, :k], augmented[:k, k:] = linear, np.eye(k)
        phi = scipy.linalg.expm(augmented)[:k, k:]
        algebra = np.zeros_like(matrix)
        algebra[:k, :k], algebra[:k, k:] = linear, np.linalg.solve(phi, matrix[:k, k:])
        return self.vee(algebra)

    def act(self, matrix, p):
        if self.has_translation:
            k = self.space
            return matrix[:k, :k] @ p + matrix[:k, k]
        return matrix @ p

    def adjoint(self, matrix):
        """Column k is `vee(X hat(e_k) X⁻¹)`."""
        inv = np.linalg.inv(matrix)
        return np.stack([self.vee(matrix @ self.hat(e) @ inv) for e in np.eye(self.dim)], axis=1)


def _se2_hat(xi):
    m = np.zeros((3, 3))
    m[:2, :2] = skew2(xi[2])
    m[:2, 2] = xi[:2]
    return m


def _se2_vee(m):
    return np.array([m[0, 2], m[1, 2], 0.5 * (m[1, 0] - m[0, 1])])


def _se3_hat(xi):
    m = np.zeros((4, 4))
    m[:3, :3] = skew3(xi[3:])
    m[:3, 3] = xi[:3]
    return m


def _se3_vee(m):
    return np.concatenate([m[:3, 3], unskew3(m[:3, :3])])


def se23_hat(xi):
    """`[[ω]×, ρp, ρv; 0, 0, 0]` for the tangent `(ρp, ω, ρv)` (5×5)."""
    m = np.zeros((5, 5))
    m[:3, :3] = skew3(xi[3:6])
    m[:3, 3], m[:3, 4] = xi[:3], xi[6:]
    return m


def se23_vee(m):
    return np.concatenate([m[:3, 3], unskew3(m[:3, :3]), m[:3, 4]])


def sim3_hat(xi):
    """`[[ω]× + σI, v; 0, 0]` for the tangent `(v, ω, σ)`."""
    m = np.zeros((4, 4))
    m[:3, :3] = skew3(xi[3:6]) + xi[6] * np.eye(3)
    m[:3, 3] = xi[:3]
    return m


def sim3_vee(m):
    """`(v, ω, σ)`: ω from the skew part of the linear block, σ a third of its trace."""
    return np.concatenate([m[:3, 3], unskew3(m[:3, :3]), [np.trace(m[:3, :3]) / 3.0]])


def _so2_constructors(dtype):
    return {"from_angle": SO2.from_angle(jnp.asarray([0.3, -2.0], dtype))}


def _se2_constructors(dtype):
    x, y = jnp.asarray(1.0, dtype), jnp.asarray([0.5, -2.0], dtype)
    return {
        "from_xy_theta numbers": SE2.from_xy_theta(x, y, 0.5),
        "from_xy_theta arrays": SE2.from_xy_theta(x, y, jnp.asarray(0.5, dtype)),
        "from_rotation_and_translation": SE2.from_rotation_and_translation(
            SO2.from_angle(jnp.asarray(0.3, dtype)), jnp.asarray([1.0, 2.0], dtype)
        ),
    }


def _so3_constructors(dtype):
    rotvec = jnp.asarray([0.1, -0.4, 0.3], dtype)
    return {
        "from_rpy numbers": SO3.from_rpy(jnp.asarray(0.1, dtype), jnp.asarray(0.2, dtype), 0.5),
        "from_rpy one array": SO3.from_rpy(0.1, jnp.asarray([0.2, 0.4], dtype), 0),
        "from_rotvec": SO3.from_rotvec(rotvec),
        "from_xyzw": SO3.from_xyzw(jnp.asarray([0.0, 0.6, 0.0, 0.8], dtype)),
    }


def _se3_constructors(dtype):
    rotation, t = SO3.exp(jnp.asarray([0.1, -0.4, 0.3], dtype)), jnp.asarray([1.0, 2.0, 3.0], dtype)
    return {
        "from_rotation_and_translation": SE3.from_rotation_and_translation(rotation, t),
        "from_rotation": SE3.from_rotation(rotation),
        "from_translation": SE3.from_translation(t),
    }


def _sim3_constructors(dtype):
    rotation, t = SO3.exp(jnp.asarray([0.1, -0.4, 0.3], dtype)), jnp.asarray([1.0, 2.0, 3.0], dtype)
    return {
        "from_rotation_translation_scale number": Sim3.from_rotation_translation_scale(
            rotation, t, 2.0
        ),
        "from_rotation_translation_scale default": Sim3.from_rotation_translation_scale(
            rotation, t
        ),
        "from_rotation_translation_scale array": Sim3.from_rotation_translation_scale(
            rotation, t, jnp.asarray(2.0, dtype)
        ),
        "from_se3 number": Sim3.from_se3(SE3.from_rotation_and_translation(rotation, t), 3.0),
        "from_scale": Sim3.from_scale(jnp.asarray([0.5, 2.0], dtype)),
    }


GROUPS = [
    GroupSpec(
        "SO2",
        SO2,
        (0,),
        (),
        hat=lambda xi: skew2(xi[0]),
        vee=lambda m: np.array([0.5 * (m[1, 0] - m[0, 1])]),
        rotation_parameters=2,
        constructors=_so2_constructors,
    ),
    GroupSpec(
        "SE2",
        SE2,
        (2,),
        (0, 1),
        hat=_se2_hat,
        vee=_se2_vee,
        rotation_parameters=2,
        constructors=_se2_constructors,
    ),
    GroupSpec(
        "SO3",
        SO3,
        (0, 1, 2),
        (),
        hat=skew3,
        vee=unskew3,
        rotation_parameters=4,
        constructors=_so3_constructors,
    ),
    GroupSpec(
        "SE3",
        SE3,
        (3, 4, 5),
        (0, 1, 2),
        hat=_se3_hat,
        vee=_se3_vee,
        rotation_parameters=4,
        constructors=_se3_constructors,
    ),
    GroupSpec(
        "Sim3",
        Sim3,
        (3, 4, 5),
        (0, 1, 2),
        hat=sim3_hat,
        vee=sim3_vee,
        rotation_parameters=4,
        scale_index=(6,),
        constructors=_sim3_constructors,
    ),
]
GROUPS.append(
    GroupSpec(
        "SE23",
        SE23,
        (3, 4, 5),
        (0, 1, 2, 6, 7, 8),
        hat=se23_hat,
        vee=se23_vee,
        rotation_parameters=4,
        constructors=lambda dtype: {
            "from_pose_and_velocity": SE23.from_pose_and_velocity(
                SE3.exp(jnp.asarray([1.0, 2.0, 3.0, 0.1, -0.4, 0.3], dtype)),
                jnp.asarray([0.5, -1.0, 2.0], dtype),
            )
        },
    )
)
GROUP_IDS = [spec.name for spec in GROUPS]


# ---- regimes of test points ----------------------------------------------------------------------

NEAR_PI = np.pi - 1e-6  # log's derivative is singular only at π itself

REGIMES = (
    "identity",
    "tiny",
    "translation",
    "small_rotation",
    "near_pi",
    "random",
    "random_2",
    "random_3",
    "random_large",
    "scale",  # groups with a scale only: translation and log-scale, no rotation
    "pure_scale",  # groups with a scale only: log-scale below 1, no rotation or translation
    "translation_scale",  # groups with a scale only: translation and a log-scale below 1
)
SCALE_REGIMES = ("scale", "pure_scale", "translation_scale")


def regimes_for(spec: GroupSpec) -> tuple:
    """The regimes that make sense for a group (pure translations only for groups with a
    translation, translation and scale only for groups with a scale)."""
    return tuple(
        r
        for r in REGIMES
        if (spec.has_translation or r != "translation")
        and (spec.has_scale or r not in SCALE_REGIMES)
    )


def _rotation_tangent(spec: GroupSpec, rng, angle: float):
    axis = rng.normal(size=len(spec.rotation_index))
    return angle * axis / np.linalg.norm(axis)


# The log-scale σ of each regime (groups with a scale; drawn after the other coordinates, so that
# the other groups' test points do not depend on it). They cover each branch of Sim3's W
# coefficients: σ = θ = 0 (pure translation), |σ| > 1 with θ = 0 ("scale"), the joint series
# (σ and θ ~1e-4), θ² > σ² (near π, random_large) and σ² > θ² > 1 (some random ones).
def _log_scale(regime: str, rng) -> float:
    if regime == "translation":
        return 0.0
    if regime == "scale":
        return 1.3 * rng.choice([-1.0, 1.0])
    if regime == "pure_scale":
        return 0.7
    if regime == "translation_scale":
        return -0.6
    if regime == "small_rotation":
        return 1e-4 * rng.uniform(-1.0, 1.0)
    if regime == "near_pi":
        return 0.4
    if regime == "random_large":
        return 2.0 * rng.choice([-1.0, 1.0])
    return rng.uniform(-1.5, 1.5)


def regime_tangent(spec: GroupSpec, regime: str, seed: int = 0) -> np.ndarray:
    """A tangent ξ whose `Exp` is a point of the named regime (deterministic per seed)."""
    rng = np.random.default_rng([seed, REGIMES.index(regime), *map(ord, spec.name)])
    xi = np.zeros(spec.dim)
    rot, trans = list(spec.rotation_index), list(spec.translation_index)
    translation = rng.normal(size=len(trans))
    if regime == "identity":
        return xi
    if regime == "tiny":
        direction = rng.normal(size=spec.dim)
        return 1e-9 * direction / np.linalg.norm(direction)
    xi[trans] = translation
    if regime == "small_rotation":
        xi[rot] = _rotation_tangent(spec, rng, 1e-4)
    elif regime == "near_pi":
        xi[rot] = _rotation_tangent(spec, rng, NEAR_PI)
    elif regime in ("random", "random_2", "random_3"):
        xi[rot] = _rotation_tangent(spec, rng, rng.uniform(0.3, 2.5))
    elif regime == "random_large":  # large translation, angle close to (but not near) π
        xi[trans] = 5.0 * translation
        xi[rot] = _rotation_tangent(spec, rng, rng.uniform(2.5, 3.0))
    elif regime == "pure_scale":
        xi[trans] = 0.0
    elif regime not in ("translation", "scale", "translation_scale"):
        raise ValueError(regime)
    if spec.has_scale:
        xi[list(spec.scale_index)] = _log_scale(regime, rng)
    return xi


# The edge regimes of the property suite (`test_properties.py`), each a hypothesis example of its
# draws: a rotation angle (a tangent's length for S2) about a fixed axis, a translation and a
# log-scale, used by every entry through its `tangent` method.
EDGE_AXIS = (0.3, -0.5, 0.81)
EDGE_EXAMPLES = {
    "identity": (0.0, (0.0, 0.0, 0.0), 0.0),
    "tiny": (1e-9, (1e-9, -2e-9, 0.5e-9), 1e-9),
    "small_rotation": (1e-4, (0.3, -1.2, 0.7), 1e-4),
    "translation": (0.0, (1.5, -0.4, 2.0), 0.0),
    "pi_minus_1e-4": (np.pi - 1e-4, (0.8, 0.1, -1.1), 0.4),
    "pi_minus_1e-6": (NEAR_PI, (-0.2, 1.4, 0.3), -0.7),
}


def regime_tangents(spec: GroupSpec, seed: int = 0) -> np.ndarray:
    """All of a group's regimes stacked on a leading batch axis, in `regimes_for` order."""
    return np.stack([regime_tangent(spec, r, seed) for r in regimes_for(spec)])


def random_tangents(spec: GroupSpec, count: int, seed: int, max_angle: float = 3.0) -> np.ndarray:
    """Random tangents with rotation angles uniform in [0, max_angle), normal translations and
    log-scales uniform in [-1, 1]."""
    rng = np.random.default_rng([seed, 1000, *map(ord, spec.name)])
    xi = np.zeros((count, spec.dim))
    for i in range(count):
        xi[i, list(spec.translation_index)] = rng.normal(size=len(spec.translation_index))
        xi[i, list(spec.rotation_index)] = _rotation_tangent(spec, rng, rng.uniform(0, max_angle))
        if spec.has_scale:
            xi[i, list(spec.scale_index)] = rng.uniform(-1.0, 1.0)
    return xi


def random_points(spec: GroupSpec, count: int, seed: int) -> np.ndarray:
    return np.random.default_rng([seed, 2000, *map(ord, spec.name)]).normal(
        size=(count, spec.space)
    )


# ---- operations checked for every group ----------------------------------------------------------
# Argument kinds: "X"  the group element Exp(ξ) at the regime's tangent ξ,
#                 "Y"  a random group element,
#                 "YX" the element Y ⊕ ξ (so that Log sees the regime: rminus, interpolate),
#                 "xi" the regime's tangent ξ, "p" a random point, "t" an interpolation parameter.
# Outputs: "group" (compared as matrices, differences by ⊖) or "array" (differences by −).


@dataclasses.dataclass(frozen=True)
class Operation:
    name: str
    kinds: tuple
    diff: tuple  # argnums differentiated
    output: str
    apply: Callable  # lieax: apply(G, *args)
    reference: Callable  # NumPy: reference(spec, *args), groups as matrices

    def __repr__(self):
        return self.name


def _interpolate_reference(spec, x, y, t):
    return x @ spec.expm(t * spec.logm(np.linalg.inv(x) @ y))


OPERATIONS = [
    Operation("exp", ("xi",), (0,), "group", lambda G, xi: G.exp(xi), lambda s, xi: s.expm(xi)),
    Operation("log", ("X",), (0,), "array", lambda G, x: x.log(), lambda s, x: s.logm(x)),
    Operation("compose", ("X", "Y"), (0, 1), "group", lambda G, x, y: x @ y, lambda s, x, y: x @ y),
    Operation(
        "inverse", ("X",), (0,), "group", lambda G, x: x.inverse(), lambda s, x: np.linalg.inv(x)
    ),
    Operation(
        "act", ("X", "p"), (0, 1), "array", lambda G, x, p: x @ p, lambda s, x, p: s.act(x, p)
    ),
    Operation(
        "between",
        ("X", "Y"),
        (0, 1),
        "group",
        lambda G, x, y: x.between(y),
        lambda s, x, y: np.linalg.inv(x) @ y,
    ),
    Operation(
        "adjoint", ("X",), (0,), "array", lambda G, x: x.adjoint(), lambda s, x: s.adjoint(x)
    ),
    Operation("as_matrix", ("X",), (0,), "array", lambda G, x: x.as_matrix(), lambda s, x: x),
    Operation(
        "rplus",
        ("Y", "xi"),
        (0, 1),
        "group",
        lambda G, x, xi: x.rplus(xi),
        lambda s, x, xi: x @ s.expm(xi),
    ),
    Operation(
        "rminus",
        ("YX", "Y"),
        (0, 1),
        "array",
        lambda G, x, y: x.rminus(y),
        lambda s, x, y: s.logm(np.linalg.inv(y) @ x),
    ),
    Operation(
        "interpolate",
        ("Y", "YX", "t"),
        (0, 1, 2),
        "group",
        lambda G, x, y, t: x.interpolate(y, t),
        _interpolate_reference,
    ),
]
OPERATION_IDS = [op.name for op in OPERATIONS]


# ---- manifolds that are not groups ---------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ManifoldSpec:
    """A manifold under test that is not a group: only `rplus`, `rminus`, `parameters()` and the
    constructors are assumed. `operations` are its own functions checked by finite differences in
    local coordinates (`Operation`s whose argument kinds are "Y" a random point, "YX" the point
    `Y ⊕ ξ`, "xi" the tangent ξ, "R" a random SO3 rotation; no NumPy reference)."""

    name: str
    cls: type
    base: Callable  # array from `random_base` -> a point
    random_base: Callable  # seed -> NumPy array
    operations: tuple
    constructors: Callable = lambda dtype: {}

    is_group = False
    has_translation = has_scale = False

    def __repr__(self):
        return self.name

    @property
    def dim(self) -> int:
        return self.cls.tangent_dim

    def tangent(self, angle, axis, translation, log_scale) -> np.ndarray:
        """A tangent of length `angle` in the direction of `axis`'s first two coordinates."""
        direction = np.asarray(axis, dtype=float)[: self.dim]
        norm = np.linalg.norm(direction)
        direction = direction / norm if norm > 0 else np.eye(self.dim)[0]
        return angle * direction


def _s2_operation(name, kinds, apply):
    return Operation(name, kinds, tuple(range(len(kinds))), "element", apply, None)


S2_SPEC = ManifoldSpec(
    "S2",
    S2,
    base=S2.from_vector,
    random_base=lambda seed: np.random.default_rng([seed, 3000]).normal(size=3),
    operations=(
        _s2_operation("rplus", ("Y", "xi"), lambda M, p, xi: p.rplus(xi)),
        _s2_operation("rminus", ("YX", "Y"), lambda M, q, p: q.rminus(p)),
        _s2_operation("error", ("Y", "YX"), lambda M, p, q: p.error(q)),
        _s2_operation("distance", ("Y", "YX"), lambda M, p, q: p.distance(q)),
        _s2_operation("rotate", ("R", "Y"), lambda M, r, p: p.rotate(r)),
        _s2_operation("unit_vector", ("Y",), lambda M, p: p.unit_vector()),
    ),
    constructors=lambda dtype: {
        "from_vector": S2.from_vector(jnp.asarray([[0.0, 3.0, 4.0], [1.0, 0.0, 0.0]], dtype))
    },
)
MANIFOLDS = [*GROUPS, S2_SPEC]
MANIFOLD_IDS = [spec.name for spec in MANIFOLDS]


def build_arguments(spec: GroupSpec, op: Operation, xis, seed: int = 1):
    """An operation's arguments for a batch of tangents `xis` (shape `(R, d)`): the lieax objects
    (float64, batch `(R,)`) and, per element, the NumPy arguments (groups as matrices). "Y" elements,
    points and interpolation parameters are random (deterministic per seed)."""
    G = spec.cls
    count = len(xis)
    etas = random_tangents(spec, count, seed=seed)
    points = random_points(spec, count, seed=seed + 1)
    ts = np.linspace(0.15, 0.85, count)
    lieax_args, numpy_args = [], []
    for kind in op.kinds:
        if kind == "X":
            lieax_args.append(G.exp(jnp.asarray(xis)))
            numpy_args.append([spec.expm(x) for x in xis])
        elif kind == "Y":
            lieax_args.append(G.exp(jnp.asarray(etas)))
            numpy_args.append([spec.expm(e) for e in etas])
        elif kind == "YX":
            lieax_args.append(G.exp(jnp.asarray(etas)) @ G.exp(jnp.asarray(xis)))
            numpy_args.append([spec.expm(e) @ spec.expm(x) for e, x in zip(etas, xis)])
        elif kind == "xi":
            lieax_args.append(jnp.asarray(xis))
            numpy_args.append(list(xis))
        elif kind == "p":
            lieax_args.append(jnp.asarray(points))
            numpy_args.append(list(points))
        elif kind == "t":
            lieax_args.append(jnp.asarray(ts))
            numpy_args.append(list(ts))
        else:
            raise ValueError(kind)
    return tuple(lieax_args), [list(element) for element in zip(*numpy_args)]


# ---- tolerances ----------------------------------------------------------------------------------

# float64: lieax Jacobians against central finite differences on matrices (step FD_STEP, or
# FD_STEP_NEAR_PI in the near-π regime so that no step crosses π); compared as
# |J - J_fd| <= FD_ATOL + FD_RTOL * max|J_fd|.
FD_STEP = 1e-6
FD_STEP_NEAR_PI = 1e-7
FD_ATOL = 1e-7
FD_RTOL = 1e-7

# float64: values against the matrix formulas and algebraic identities.
VALUE_ATOL_F64 = 1e-10

# float32: documented accuracy of each operation: the largest absolute error against the float64
# result (values) and against the float64 Jacobian (Jacobians), relative to max(1, |reference|),
# with float32 inputs that are the float64 inputs rounded, in every regime (π - 1e-6 included;
# translations up to ~7, points of order 1). Measured maxima over SO2, SE2, SO3, SE3 on the
# regime batch (JAX 0.10.2, CPU), value / Jacobian:
#   exp 2.9e-7 / 1.7e-7, log 8.0e-8 / 2.0e-7, compose 1.5e-7 / 1.3e-7, inverse 1.1e-7 / 1.4e-7,
#   act 1.5e-7 / 1.7e-7, between 1.5e-7 / 2.4e-7, adjoint 1.1e-7 / 1.1e-7,
#   as_matrix 1.1e-7 / 1.1e-7, rplus 2.6e-7 / 2.8e-7, rminus 1.3e-7 / 3.4e-7,
#   interpolate 3.3e-7 / 2.0e-6, right_jacobian 1.7e-7 / 2.0e-7 (value / derivative),
#   right_jacobian_inverse 1.7e-7 / 4.6e-7;
# a sweep over 64 random elements (angles up to 3 rad, translations ~1) gave at most
# 3.5e-7 / 5.4e-7. interpolate's Jacobian with respect to its first argument is a small
# difference of terms of the size of the translation (SE3, 2.5 rad, |t| ~ 4: |J| = 0.27 from terms
# ~4), hence its larger float32 error there. Sim3 on its regime batch (scales up to e^±2,
# translations up to ~7 times the scale): rminus 4.0e-7 / 9.7e-7, interpolate 3.3e-7 / 1.9e-6, the
# others at most 2.9e-7 / 3.5e-7. The tolerances leave a margin of 4x or more (5x for the rigid
# groups).
FLOAT32_TOLERANCE = {
    # operation: (value, Jacobian)
    "exp": (2e-6, 2e-6),
    "log": (2e-6, 3e-6),
    "compose": (2e-6, 3e-6),
    "inverse": (2e-6, 2e-6),
    "act": (2e-6, 2e-6),
    "between": (2e-6, 3e-6),
    "adjoint": (2e-6, 2e-6),
    "as_matrix": (2e-6, 2e-6),
    "rplus": (3e-6, 4e-6),
    "rminus": (3e-6, 4e-6),
    "interpolate": (3e-6, 1e-5),
    "right_jacobian": (2e-6, 2e-6),
    "right_jacobian_inverse": (2e-6, 3e-6),
}

# lieax.groups._series.g(n, s): largest error of g_n and of its first two derivatives, relative to
# 1/n! (the size of g_n), over s in [0, 40]. The series is summed below s = 4; above, the
# recurrence g_{n+2} = (1/n! - g_n) / s from cos / sin loses about half a digit per order just
# above s = 4. Measured float64 (value, g', g''): n <= 3 below 4.5e-16; n = 4: 6.7e-16;
# 5: 1.4e-15; 6: 4.8e-15; 7: 1.4e-14; 8: 9.1e-14. float32 (value, g'): n <= 3 below 2.4e-7;
# 4: 3.2e-7; 5: 8.5e-7; 6: 2.6e-6; 7: 8.4e-6; 8: 3.9e-5. The kernels use g_0 ... g_5, and
# g_{n+1}, g_{n+2} in derivatives.
SERIES_TOLERANCE = {
    # n: (float64, float32)
    0: (1e-15, 1e-6),
    1: (1e-15, 1e-6),
    2: (1e-15, 1e-6),
    3: (1e-15, 1e-6),
    4: (2e-15, 1.5e-6),
    5: (5e-15, 4e-6),
    6: (2e-14, 1e-5),
    7: (5e-14, 4e-5),
    8: (3e-13, 1.5e-4),
}


# ---- finite differences on matrices --------------------------------------------------------------


def log_near_identity(matrix):
    """`logm(M)` for `M` within ~1e-4 of the identity (batched): the series
    `E - E²/2 + E³/3 - ...` with `E = M - I`, exact to float64 rounding there (and much faster than
    `scipy.linalg.logm`, which the finite differences would call thousands of times)."""
    e = matrix - np.eye(matrix.shape[-1])
    power, total = e, e.copy()
    for k in range(2, 7):
        power = power @ e
        total += (-1) ** (k + 1) * power / k
    return total


def _perturb(spec: GroupSpec, kind: str, arg, direction, step):
    """`arg ⊕ step·direction` on matrices (groups) or by addition (arrays)."""
    if kind in ("X", "Y", "YX"):
        return arg @ spec.expm(step * direction)
    return arg + step * direction.reshape(np.shape(arg))


def _difference(spec: GroupSpec, output: str, value, base):
    """`value ⊖ base`: `vee(log(base⁻¹ value))` for groups, `value - base` (raveled) for arrays."""
    if output == "group":
        return spec.vee(log_near_identity(np.linalg.solve(base, value)))
    return np.ravel(value - base)


def fd_jacobians(spec: GroupSpec, op: Operation, args, step: float) -> list:
    """Central finite-difference Jacobians of `op.reference` at one element (`args` as NumPy, groups
    as matrices), one `(out_size, in_size)` block per differentiated argument, in local coordinates:
    column k is `(f(x ⊕ εe_k) ⊖ f(x) - f(x ⊕ -εe_k) ⊖ f(x)) / 2ε`, with `x ⊕ δ = x·expm(hat(δ))`
    for group arguments and `x + δ` for arrays."""
    base = op.reference(spec, *args)
    blocks = []
    for i in op.diff:
        size = spec.dim if op.kinds[i] in ("X", "Y", "YX") else int(np.size(args[i]))
        columns = []
        for direction in np.eye(size):
            sides = []
            for sign in (1.0, -1.0):
                moved = list(args)
                moved[i] = _perturb(spec, op.kinds[i], args[i], direction, sign * step)
                sides.append(_difference(spec, op.output, op.reference(spec, *moved), base))
            columns.append((sides[0] - sides[1]) / (2.0 * step))
        blocks.append(np.stack(columns, axis=1))
    return blocks


def fd_step(regime: str) -> float:
    return FD_STEP_NEAR_PI if regime == "near_pi" else FD_STEP


def assert_close_to_fd(actual, expected, what: str):
    """`|J - J_fd| <= FD_ATOL + FD_RTOL * max|J_fd|`, entries finite."""
    actual, expected = np.asarray(actual), np.asarray(expected)
    assert actual.shape == expected.shape, f"{what}: shape {actual.shape} != {expected.shape}"
    assert np.all(np.isfinite(actual)), f"{what}: non-finite entries\n{actual}"
    error = np.max(np.abs(actual - expected), initial=0.0)
    bound = FD_ATOL + FD_RTOL * np.max(np.abs(expected), initial=0.0)
    assert error <= bound, (
        f"{what}: max |J - J_fd| = {error:.3g} > {bound:.3g}\n"
        f"lieax:\n{actual}\nfinite differences:\n{expected}"
    )
