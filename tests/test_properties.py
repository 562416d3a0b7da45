r"""Property-based tests (hypothesis) of every registered group and manifold, float64 and float32.

Each property is drawn over a rotation angle in $[0, \pi - 10^{-3}]$ about a random axis, a
translation, a log-scale and a seed for the other random elements, mapped to a tangent by each
registry entry (`registry.MANIFOLDS`), with the edge regimes as explicit examples
(`registry.EDGE_EXAMPLES`: identity, 1e-9 from it, 1e-4 rad, pure translation, π - 1e-4,
π - 1e-6):

- group axioms: $XX^{-1} = e$, $(XY)Z = X(YZ)$, $\mathrm{Exp}(\mathrm{Log}\,X) = X$,
  $\mathrm{Log}(\mathrm{Exp}\,\xi) = \xi$ (angles below π); the adjoint identity
  $X\,\mathrm{Exp}(\eta) = \mathrm{Exp}(\mathrm{Ad}_X \eta)\,X$; the action as the matrix
  product, $(XY)p = X(Yp)$;
- for every manifold: $(Y \oplus \xi) \ominus Y = \xi$, $Y \oplus (X \ominus Y) = X$,
  $Y \oplus 0 = Y$; `lieax.jacobian` of the main operations against central finite differences in
  local coordinates (float64; lieax's own ⊕ / ⊖ as the charts); gradients finite at every draw;
- float32 in, float32 out for every operation and constructor (Python numbers included);
  batch shapes broadcast like NumPy's, and shapes that do not are a `ValueError` naming them.

Each (entry, dtype) compiles one jitted function that every example of a property calls. The
default profile ("ci") runs a few examples per property; `HYPOTHESIS_PROFILE=long` runs 200, and
the finite-difference Jacobians (marked `slow`; in every run `test_jacobians.py` checks the same
operations against NumPy matrix formulas at the registry's regimes).
"""

import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _stacked import stacked, unstacked
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import BroadcastableShapes, mutually_broadcastable_shapes
from registry import (
    EDGE_AXIS,
    EDGE_EXAMPLES,
    GROUP_IDS,
    GROUPS,
    MANIFOLD_IDS,
    MANIFOLDS,
    OPERATIONS,
)

import lieax

settings.register_profile(
    "ci",
    max_examples=6,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile("long", max_examples=200, deadline=None)
PROFILE_NAME = os.environ.get("HYPOTHESIS_PROFILE", "ci")
PROFILE = settings.get_profile(PROFILE_NAME)
# what runs only in the long profile (CI's budget; what covers it in every run is named where used)
long_profile_only = [
    pytest.mark.slow,
    pytest.mark.skipif(PROFILE_NAME != "long", reason="long profile: HYPOTHESIS_PROFILE=long"),
]

DTYPES = [jnp.float64, jnp.float32]
DTYPE_IDS = ["float64", "float32"]
# values: |actual - expected| <= tolerance * max(1, |expected|)
VALUE_TOLERANCE = {jnp.float64: 1e-9, jnp.float32: 3e-5}
FD_STEP, FD_STEP_NEAR_PI = 1e-6, 1e-7
FD_TOLERANCE = 1e-6  # |J - J_fd| <= FD_TOLERANCE * max(1, |J_fd|)

# the operations whose Jacobians are checked at every draw (all of S2's)
MAIN_OPERATIONS = ("exp", "log", "act", "rminus")
# operations with a kink at ξ = 0 (the distance between coincident directions): within 1e-2 of it
# central differences are meaningless (their error grows like step² / |ξ|), so they are not checked
KINKED_AT_ZERO = ("distance",)

parametrize_manifolds = pytest.mark.parametrize("spec", MANIFOLDS, ids=MANIFOLD_IDS)
parametrize_groups = pytest.mark.parametrize("spec", GROUPS, ids=GROUP_IDS)
parametrize_dtypes = pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)


def draws(test):
    """`@given` over the draws, with every edge regime as an `@example`, under the profile."""
    axis = st.tuples(*3 * [st.floats(-1.0, 1.0)]).filter(
        lambda a: abs(a[0]) > 1e-3 and np.linalg.norm(a[:2]) > 0.1
    )
    test = given(
        angle=st.floats(0.0, np.pi - 1e-3),
        axis=axis,
        translation=st.tuples(*3 * [st.floats(-3.0, 3.0)]),
        log_scale=st.floats(-1.5, 1.5),
        seed=st.integers(0, 2**20),
    )(test)
    for angle, translation, log_scale in EDGE_EXAMPLES.values():
        test = example(
            angle=angle, axis=EDGE_AXIS, translation=translation, log_scale=log_scale, seed=0
        )(test)
    return PROFILE(test)


def inputs(spec, dtype, angle, axis, translation, log_scale, seed):
    """The arrays of one draw: ξ (the regime's tangent), the bases of two random elements, a point,
    an interpolation parameter and a rotation tangent."""
    rng = np.random.default_rng([seed, 4000])
    arrays = {
        "xi": spec.tangent(angle, axis, translation, log_scale),
        "eta": spec.random_base(seed),
        "zeta": spec.random_base(seed + 1),
        "p": rng.normal(size=3 if not spec.is_group else spec.space),
        "t": rng.uniform(0.1, 0.9),
        "omega": rng.normal(size=3),
    }
    return {key: jnp.asarray(value, dtype) for key, value in arrays.items()}


def assert_close(actual, expected, tolerance, what):
    actual, expected = np.asarray(actual, np.float64), np.asarray(expected, np.float64)
    assert actual.shape == expected.shape, f"{what}: shape {actual.shape} != {expected.shape}"
    assert np.all(np.isfinite(actual)), f"{what}: not finite\n{actual}"
    scale = max(1.0, float(np.max(np.abs(expected), initial=0.0)))
    error = float(np.max(np.abs(actual - expected), initial=0.0))
    assert error <= tolerance * scale, f"{what}: error {error:.3g} > {tolerance * scale:.3g}"


def _array(value):
    return value.parameters() if isinstance(value, lieax.AbstractManifold) else value


# ---- values: axioms, round trips, adjoint, action ------------------------------------------------


@functools.cache
def value_checks(name, dtype):
    """For entry `name`: pairs (actual, expected) of every identity at one draw, jitted."""
    spec = MANIFOLDS[MANIFOLD_IDS.index(name)]

    def evaluate(a):
        # Calls of the same operation share one call on stacked cases (the same values, a
        # program about half the size of one with a copy of the kernel per call).
        if spec.is_group:
            G = spec.cls
            x, y, z = unstacked(G.exp(jnp.stack([a["xi"], a["eta"], a["zeta"]])), 3)
        else:
            y = spec.base(a["eta"])
        moved, y_plus_zero = unstacked(y.rplus(jnp.stack([a["xi"], jnp.zeros_like(a["xi"])])), 2)
        back, moved_minus_moved = unstacked(stacked(moved, moved).rminus(stacked(y, moved)), 2)
        pairs = {
            "(Y ⊕ ξ) ⊖ Y = ξ": (back, a["xi"]),
            "Y ⊕ ((Y ⊕ ξ) ⊖ Y) = Y ⊕ ξ": (y.rplus(back).parameters(), moved.parameters()),
            "Y ⊕ 0 = Y": (y_plus_zero.parameters(), y.parameters()),
            "X ⊖ X = 0": (moved_minus_moved, jnp.zeros_like(a["xi"])),
        }
        if not spec.is_group:
            norm = jnp.linalg.norm(moved.parameters(), axis=-1)
            pairs["|Y ⊕ ξ| = 1"] = (norm, jnp.ones_like(norm))
            return pairs
        m = x.as_matrix()
        eye = jnp.eye(spec.n, dtype=dtype)
        log_x = x.log()
        exp_log_x, exp_ad = unstacked(G.exp(jnp.stack([log_x, x.adjoint() @ a["eta"]])), 2)
        pairs |= {
            "X X⁻¹ = e": ((x @ x.inverse()).as_matrix(), eye),
            "X⁻¹ X = e": ((x.inverse() @ x).as_matrix(), eye),
            "(X Y) Z = X (Y Z)": (((x @ y) @ z).as_matrix(), (x @ (y @ z)).as_matrix()),
            "Exp(Log X) = X": (exp_log_x.as_matrix(), m),
            "Log(Exp ξ) = ξ": (log_x, a["xi"]),
            "X Exp(η) = Exp(Ad_X η) X": ((x @ y).as_matrix(), (exp_ad @ x).as_matrix()),
            "(X Y) p = X (Y p)": ((x @ y) @ a["p"], x @ (y @ a["p"])),
            "as_matrix(X Y) = M_X M_Y": ((x @ y).as_matrix(), m @ y.as_matrix()),
        }
        pairs["X @ p = M p"] = (x @ a["p"], m)  # the expected value: the registry's formula on M
        return pairs

    return jax.jit(evaluate)


@parametrize_dtypes
@parametrize_manifolds
@draws
def test_identities(spec, dtype, angle, axis, translation, log_scale, seed):
    """Group axioms, the adjoint identity and the action (groups); ⊕ / ⊖ round trips (every
    manifold), within `VALUE_TOLERANCE` of the dtype."""
    a = inputs(spec, dtype, angle, axis, translation, log_scale, seed)
    for what, (actual, expected) in value_checks(spec.name, dtype)(a).items():
        if what == "X @ p = M p":
            expected = spec.act(np.asarray(expected, np.float64), np.asarray(a["p"], np.float64))
        assert actual.dtype == dtype, f"{spec} {what}: {actual.dtype}"
        assert_close(actual, expected, VALUE_TOLERANCE[dtype], f"{spec} {dtype.__name__} {what}")


# ---- Jacobians against finite differences in local coordinates (float64) -----------------------


def _operations(spec):
    if not spec.is_group:
        return spec.operations
    return tuple(op for op in OPERATIONS if op.name in MAIN_OPERATIONS)


def _arguments(spec, op, a):
    G = spec.cls
    y = spec.base(a["eta"])
    kinds = {
        "X": lambda: G.exp(a["xi"]),
        "Y": lambda: y,
        "YX": lambda: y.rplus(a["xi"]),
        "xi": lambda: a["xi"],
        "p": lambda: a["p"],
        "t": lambda: a["t"],
        "R": lambda: lieax.SO3.exp(a["omega"]),
    }
    return [kinds[kind]() for kind in op.kinds]


def _difference(value, base):
    if isinstance(base, lieax.AbstractManifold):
        return value.rminus(base)
    return jnp.ravel(value - base)


def _central_differences(f, args, argnum, step):
    """Column k: `(f(x ⊕ εe_k) ⊖ f(x) - f(x ⊕ -εe_k) ⊖ f(x)) / 2ε` for argument `argnum`."""
    base = f(*args)
    arg = args[argnum]
    size = arg.tangent_dim if isinstance(arg, lieax.AbstractManifold) else arg.size

    def moved(direction):
        shifted = list(args)
        if isinstance(arg, lieax.AbstractManifold):
            shifted[argnum] = arg.rplus(direction)
        else:
            shifted[argnum] = arg + direction.reshape(arg.shape)
        return _difference(f(*shifted), base)

    directions = step * jnp.eye(size, dtype=jnp.float64)
    plus, minus = jax.vmap(moved)(directions), jax.vmap(moved)(-directions)
    return ((plus - minus) / (2.0 * step)).T


@functools.cache
def jacobian_checks(name):
    """For entry `name`: per main operation and argument, (lieax.jacobian, finite differences)."""
    spec = MANIFOLDS[MANIFOLD_IDS.index(name)]

    def evaluate(a, step):
        out = {}
        for op in _operations(spec):
            f = functools.partial(op.apply, spec.cls)
            args = _arguments(spec, op, a)
            blocks = lieax.jacobian(f, op.diff)(*args)
            for position, argnum in enumerate(op.diff):
                block = blocks[position]
                fd = _central_differences(f, args, argnum, step)
                out[f"{op.name} d/d(arg {argnum})"] = (block.reshape(fd.shape), fd)
        return out

    return jax.jit(evaluate)


@pytest.mark.parametrize(
    "spec", [pytest.param(spec, marks=long_profile_only) for spec in MANIFOLDS], ids=MANIFOLD_IDS
)
@draws
def test_jacobians_match_finite_differences(spec, angle, axis, translation, log_scale, seed):
    """`lieax.jacobian` of the main operations (all of S2's) against central finite differences in
    local coordinates, float64 (step 1e-7 within 1e-5 of π, where a larger one would cross π;
    `KINKED_AT_ZERO` operations only 1e-2 or more from their kink)."""
    a = inputs(spec, jnp.float64, angle, axis, translation, log_scale, seed)
    step = FD_STEP_NEAR_PI if angle > np.pi - 1e-5 else FD_STEP
    for what, (actual, expected) in jacobian_checks(spec.name)(a, step).items():
        if what.split(" ")[0] in KINKED_AT_ZERO and angle < 1e-2:
            continue
        assert_close(actual, expected, FD_TOLERANCE, f"{spec}.{what}")


# ---- gradients are finite ------------------------------------------------------------------------


def _scalar(spec, a, xi, params):
    """A sum over the main operations' outputs at `X = Exp(ξ)` (groups), `Y ⊕ ξ` and the raw
    parameters `params` of a point (exp, log, rplus, rminus, act, the right Jacobian)."""
    cls = spec.cls
    if spec.is_group:  # Exp of ξ and η in one call (one copy of the kernel)
        x, y = unstacked(cls.exp(jnp.stack([xi, a["eta"]])), 2)
    else:
        y = spec.base(a["eta"])
    raw = cls(params)
    moved = y.rplus(xi)
    # (Y ⊕ ξ) ⊖ Y and raw ⊖ Y in one call
    differences = cls(jnp.stack([moved.parameters(), params])).rminus(y)
    terms = [moved.parameters(), differences[0], differences[1]]
    if spec.is_group:
        terms += [
            x.parameters(),
            x.log(),
            raw @ a["p"],
            cls.right_jacobian(xi),
        ]
    else:
        terms += [raw.error(moved), raw.distance(moved), raw.rotate(lieax.SO3.exp(a["omega"]))]
        terms[-1] = terms[-1].parameters()
    return sum(jnp.sum(jnp.sin(term)) for term in terms)


@functools.cache
def gradient_checks(name, dtype):
    spec = MANIFOLDS[MANIFOLD_IDS.index(name)]

    def evaluate(a):
        params = spec.base(a["eta"]).rplus(a["xi"]).parameters()
        if spec.is_group:
            params = spec.cls.exp(a["xi"]).parameters()
        scalar = functools.partial(_scalar, spec, a)
        by_tangent, by_parameters = jax.grad(scalar, (0, 1))(a["xi"], params)
        return {"ξ": by_tangent, "parameters": by_parameters}

    return jax.jit(evaluate)


@pytest.mark.parametrize(
    "dtype",
    [pytest.param(jnp.float64, marks=long_profile_only), jnp.float32],
    ids=DTYPE_IDS,
)
@parametrize_manifolds
@draws
def test_gradients_are_finite(spec, dtype, angle, axis, translation, log_scale, seed):
    """`jax.grad` (by a tangent and by raw parameters) of a scalar through the main operations
    is finite (never NaN) at every draw, the edge regimes included (float64 in the long profile:
    `test_second_order.py` checks float64 gradients at the registry's regimes in every run)."""
    a = inputs(spec, dtype, angle, axis, translation, log_scale, seed)
    for what, gradient in gradient_checks(spec.name, dtype)(a).items():
        assert gradient.dtype == dtype, f"{spec} gradient by {what}: {gradient.dtype}"
        assert np.all(np.isfinite(gradient)), f"{spec} {dtype.__name__} gradient by {what}"


# ---- dtypes ------------------------------------------------------------------------------------


def _group_outputs(spec, dtype):
    G = spec.cls
    x = G.sample_uniform(jax.random.key(0), (4,), dtype=dtype)
    y = G.exp(jnp.full((4, spec.dim), 0.3, dtype))
    xi = y.log()
    points = jnp.ones((4, spec.space), dtype)
    return {
        "identity": G.identity((2,), dtype=dtype),
        "sample_uniform": x,
        "exp": y,
        "from_matrix": G.from_matrix(x.as_matrix()),
        "from parameters": G(x.parameters()),
        "normalize": x.normalize(),
        "log": xi,
        "compose": x @ y,
        "inverse": x.inverse(),
        "act": x @ points,
        "act on one point": x @ jnp.ones(spec.space, dtype),
        "between": x.between(y),
        "adjoint": x.adjoint(),
        "as_matrix": x.as_matrix(),
        "rplus": x.rplus(xi),
        "rminus": x.rminus(y),
        "interpolate Python number": x.interpolate(y, 0.3),
        "interpolate Python int": x.interpolate(y, 1),
        "interpolate NumPy float64 number": x.interpolate(y, np.float64(0.3)),
        "interpolate array": x.interpolate(y, jnp.asarray(0.3, dtype)),
        "hat": G.hat(xi),
        "vee": G.vee(G.hat(xi)),
        "right_jacobian": G.right_jacobian(xi),
        "right_jacobian_inverse": G.right_jacobian_inverse(xi),
        "left_jacobian": G.left_jacobian(xi),
        "left_jacobian_inverse": G.left_jacobian_inverse(xi),
        "jacobian": lieax.jacobian(lambda a, b: a.interpolate(b, 0.5), (0, 1))(x, y)[1],
        "jacobian rev": lieax.jacobian(lambda a, p: a @ p, (0, 1), mode="rev")(x, points)[0],
        "grad": lieax.grad(lambda a: jnp.sum(a.log() * 0.5))(x),
    }


def _manifold_outputs(spec, dtype):
    M = spec.cls
    p = M.sample_uniform(jax.random.key(0), (4,), dtype=dtype)
    xi = jnp.full((4, spec.dim), 0.3, dtype)
    q = p.rplus(xi)
    return {
        "sample_uniform": p,
        "from parameters": M(p.parameters()),
        "normalize": p.normalize(),
        "rplus": q,
        "rminus": q.rminus(p),
        "rplus numbers": p.rplus(0.5 * xi),
        **{
            op.name: op.apply(M, *_manifold_arguments(p, q, xi, dtype, op))
            for op in spec.operations
        },
        "jacobian": lieax.jacobian(lambda a, b: a.rminus(b), (0, 1))(q, p)[1],
        "grad": lieax.grad(lambda a: jnp.sum(a.parameters() * 0.5))(p),
    }


def _manifold_arguments(p, q, xi, dtype, op):
    rotation = lieax.SO3.exp(jnp.full((4, 3), 0.2, dtype))
    return [{"Y": p, "YX": q, "xi": xi, "R": rotation}[kind] for kind in op.kinds]


@parametrize_dtypes
@parametrize_manifolds
def test_dtype_is_preserved(spec, dtype):
    """float32 in, float32 out (and float64 in, float64 out) for every operation and constructor,
    Python and NumPy numbers taking the dtype of the arrays (traced only: `jax.eval_shape`)."""
    outputs = _group_outputs if spec.is_group else _manifold_outputs
    shapes = jax.eval_shape(lambda: {**outputs(spec, dtype), **spec.constructors(dtype)})
    wrong = {
        name: str(_array(value).dtype)
        for name, value in shapes.items()
        if _array(value).dtype != dtype
    }
    assert not wrong, f"{spec} {dtype.__name__} in: {wrong}"


# ---- batch shapes ----------------------------------------------------------------------------------


def _binary(spec, x, y):
    """Every binary operation of the entry between the batches `x` and `y` (the second argument, a
    tangent, points, `t` or a rotation, made from `y` so that it has `y`'s batch shape)."""
    from_y = y.parameters()[..., :1]
    out = {
        "rplus": x.rplus(jnp.broadcast_to(from_y, (*y.batch_shape, spec.dim))),
        "rminus": x.rminus(y),
    }
    if spec.is_group:
        out |= {
            "compose": x @ y,
            "between": x.between(y),
            "act": x @ jnp.broadcast_to(from_y, (*y.batch_shape, spec.space)),
            "interpolate": x.interpolate(y, 0.5),
            "interpolate t": x.interpolate(x, 0.5 * from_y[..., 0]),
        }
    else:
        out |= {
            "error": x.error(y),
            "distance": x.distance(y),
            "rotate": x.rotate(lieax.SO3.exp(y.parameters())),
        }
    return out


def _samples(spec, shape_x, shape_y, dtype):
    cls = spec.cls
    return (
        cls.sample_uniform(jax.random.key(1), shape_x, dtype=dtype),
        cls.sample_uniform(jax.random.key(2), shape_y, dtype=dtype),
    )


@parametrize_manifolds
@settings(PROFILE, max_examples=2 if PROFILE_NAME == "ci" else PROFILE.max_examples)
@given(shapes=mutually_broadcastable_shapes(num_shapes=2, max_dims=3, max_side=3))
@example(shapes=BroadcastableShapes(input_shapes=((3, 1), (4,)), result_shape=(3, 4)))
@example(shapes=BroadcastableShapes(input_shapes=((), (2, 3)), result_shape=(2, 3)))
def test_batch_shapes_broadcast(spec, shapes):
    """Binary operations broadcast batch shapes like NumPy (traced only)."""
    shape_x, shape_y = shapes.input_shapes
    out = jax.eval_shape(lambda: _binary(spec, *_samples(spec, shape_x, shape_y, jnp.float32)))
    for name, value in out.items():
        value = _array(value)
        batch = value.shape[: len(shapes.result_shape)]
        assert batch == shapes.result_shape, f"{spec}.{name}: {value.shape}"
        assert value.ndim - len(shapes.result_shape) <= 1, f"{spec}.{name}: {value.shape}"


@parametrize_manifolds
def test_batch_shapes_that_do_not_broadcast(spec):
    """Shapes that do not broadcast: a `ValueError` naming both shapes, in every binary operation
    (not JAX's message from deep inside a kernel)."""
    names = jax.eval_shape(lambda: _binary(spec, *_samples(spec, (2,), (2,), jnp.float32))).keys()
    for name in names:
        with pytest.raises(ValueError, match=r"batch shapes .*\(2,\).*\(3,\)"):
            jax.eval_shape(
                lambda n=name: _binary(spec, *_samples(spec, (2,), (3,), jnp.float32))[n]
            )


@pytest.mark.parametrize(
    "spec",
    [s for s in MANIFOLDS if not s.is_group],
    ids=[s.name for s in MANIFOLDS if not s.is_group],
)
def test_broadcast_values(spec):
    """A batch `(3, 1)` against a batch `(4,)` gives, at `[i, j]`, the result for `x[i, 0]` and
    `y[j]` (the manifolds that are not groups; `test_groups.py::test_broadcasting` checks the
    groups' values)."""
    x, y = _samples(spec, (3, 1), (4,), jnp.float64)
    evaluate = jax.jit(functools.partial(_binary, spec))
    out = evaluate(x, y)
    for i, j in ((0, 0), (2, 3), (1, 2)):
        expected = evaluate(x[i, 0], y[j])
        for name in out:
            np.testing.assert_allclose(
                _array(out[name])[i, j], _array(expected[name]), atol=1e-12, err_msg=name
            )
