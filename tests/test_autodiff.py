"""`lieax.jacobian` / `grad` / `value_and_jacobian` and the manifold helpers over pytrees that mix
groups and arrays.

References are central finite differences in local coordinates taken with the pytree helpers,
`f(x ⊕ εe_k) ⊖ f(x)` (`lieax.rplus` / `lieax.rminus`, which `test_groups.py` checks against matrix
formulas), evaluated under one `jit` per function.
"""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from registry import (
    FD_ATOL,
    FD_RTOL,
    GROUPS,
    SE2,
    SE3,
    SO2,
    SO3,
    random_tangents,
    regime_tangent,
)

import lieax

FD_EPS = 1e-6


# ---- helpers -------------------------------------------------------------------------------------


def tangent_size(tree) -> int:
    return lieax.tangent_dim(tree)


def dense(jac, out_tree, in_trees):
    """A `lieax.jacobian` result (result structure outside, argument structure inside) as one
    `(out_dim, in_dim)` matrix, tangent coordinates in `flatten_tangents` order."""
    out_sizes = [int(np.size(t)) for t in jax.tree_util.tree_leaves(lieax.zero_tangents(out_tree))]
    in_sizes = [
        int(np.size(t))
        for tree in in_trees
        for t in jax.tree_util.tree_leaves(lieax.zero_tangents(tree))
    ]
    blocks = jax.tree_util.tree_leaves(jac)
    assert len(blocks) == len(out_sizes) * len(in_sizes), "unexpected Jacobian structure"
    rows = []
    for i, out_size in enumerate(out_sizes):
        row = [
            np.asarray(blocks[i * len(in_sizes) + j]).reshape(out_size, in_size)
            for j, in_size in enumerate(in_sizes)
        ]
        rows.append(np.concatenate(row, axis=1))
    return np.concatenate(rows, axis=0)


def fd_dense(f, args, argnums):
    """A traceable function of `args` giving central finite differences of `f` in local
    coordinates of the arguments `argnums` (a tuple), as one `(out_dim, in_dim)` matrix."""
    sizes = [tangent_size(args[i]) for i in argnums]

    def compute(args):
        base = f(*args)

        def moved(vector):
            full, start = list(args), 0
            for i, size in zip(argnums, sizes):
                delta = lieax.unflatten_tangents(args[i], vector[start : start + size])
                full[i] = lieax.rplus(args[i], delta)
                start += size
            return lieax.flatten_tangents(lieax.rminus(f(*full), base))

        shifts = FD_EPS * jnp.eye(sum(sizes))  # ± in one vmap: one copy of `f`'s program
        plus, minus = jnp.split(jax.vmap(moved)(jnp.concatenate([shifts, -shifts])), 2)
        return ((plus - minus) / (2 * FD_EPS)).T

    return compute


def assert_fd_close(actual, expected, what):
    actual, expected = np.asarray(actual), np.asarray(expected)
    assert actual.shape == expected.shape, f"{what}: {actual.shape} != {expected.shape}"
    assert np.all(np.isfinite(actual)), f"{what}: not finite"
    error = np.max(np.abs(actual - expected), initial=0.0)
    bound = FD_ATOL + FD_RTOL * np.max(np.abs(expected), initial=0.0)
    assert error <= bound, f"{what}: max |J - J_fd| = {error:.3g} > {bound:.3g}"


def tree_allclose(a, b, atol=1e-12):
    leaves_a = jax.tree_util.tree_leaves(a, is_leaf=lambda x: isinstance(x, lieax.AbstractGroup))
    leaves_b = jax.tree_util.tree_leaves(b, is_leaf=lambda x: isinstance(x, lieax.AbstractGroup))
    assert len(leaves_a) == len(leaves_b)
    for x, y in zip(leaves_a, leaves_b):
        if isinstance(x, lieax.AbstractGroup):
            assert type(x) is type(y)
            x, y = x.as_matrix(), y.as_matrix()
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=0, atol=atol)


def element(G, seed, batch=()):
    count = math.prod(batch)
    spec = next(s for s in GROUPS if s.cls is G)
    xi = random_tangents(spec, max(count, 1), seed=seed)
    return G.exp(jnp.asarray(xi[0] if batch == () else xi.reshape(*batch, -1)))


# ---- a composite function over mixed pytrees ---------------------------------------------------


def make_state():
    state = {
        "pose": element(SE3, 1),
        "rotations": element(SO3, 2, (2,)),
        "bias": jnp.asarray([0.1, -0.2, 0.3]),
    }
    data = (element(SE2, 3), jnp.asarray([0.5, -1.5]))
    extra = element(SO2, 4)
    points = jnp.asarray(np.random.default_rng(5).normal(size=(4, 3)))
    return state, data, extra, points


def composite(state, data, extra, points):
    """Mixed inputs to mixed outputs: groups, arrays, a scalar."""
    pose, rotations, bias = state["pose"], state["rotations"], state["bias"]
    planar, offset = data
    moved = pose @ (rotations[0] @ (rotations[1] @ points)) + bias
    rotation_2d = SO2.exp(planar.log()[..., 2:] * offset[0]) @ extra
    heading = SE2.from_rotation_and_translation(rotation_2d, offset * bias[:2])
    chained = pose @ SE3.from_rotation_and_translation(rotations[1], bias)
    cost = jnp.sum(moved**2) + jnp.sum(planar.rminus(heading) ** 2)
    return {"moved": moved, "chained": chained, "heading": heading}, (cost, rotations.inverse())


@functools.cache
def composite_jacobians():
    """Forward- and reverse-mode Jacobians of `composite` with respect to its first three
    arguments, and finite differences (one jitted call)."""
    args = make_state()
    argnums = (0, 1, 2)

    @jax.jit
    def evaluate(args):
        return (
            lieax.jacobian(composite, argnums, mode="fwd")(*args),
            lieax.jacobian(composite, argnums, mode="rev")(*args),
            fd_dense(composite, args, argnums)(args),
        )

    return args, *evaluate(args)


def test_composite_jacobian_matches_finite_differences():
    args, fwd, rev, expected = composite_jacobians()
    out = composite(*args)
    in_trees = list(args[:3])
    assert_fd_close(dense(fwd, out, in_trees), expected, "fwd")
    assert_fd_close(dense(rev, out, in_trees), expected, "rev")
    for a, b in zip(jax.tree_util.tree_leaves(fwd), jax.tree_util.tree_leaves(rev)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("argnums", [(0, 1, 2), (1,), (2, 0), 2], ids=str)
def test_composite_jacobian_structure(argnums):
    """Result structure outside, the arguments inside (a tuple over `argnums` when it is a
    tuple), blocks of shape `(*out_tangent_shape, *in_tangent_shape)`."""
    args = make_state()
    jac = jax.eval_shape(lieax.jacobian(composite, argnums), *args)
    single = isinstance(argnums, int)
    selected = (argnums,) if single else argnums
    moved = jac[0]["moved"]
    if single:
        structure = jax.tree_util.tree_structure
        assert structure(moved) == structure(lieax.zero_tangents(args[argnums]))
    else:
        assert isinstance(moved, tuple) and len(moved) == len(argnums)

    def block(out, i):
        return out if single else out[selected.index(i)]

    if 0 in selected:
        assert block(moved, 0)["pose"].shape == (4, 3, 6)
        assert block(moved, 0)["rotations"].shape == (4, 3, 2, 3)
        assert block(moved, 0)["bias"].shape == (4, 3, 3)
        assert block(jac[0]["chained"], 0)["pose"].shape == (6, 6)
    if 1 in selected:
        assert block(moved, 1)[0].shape == (4, 3, 3) and block(moved, 1)[1].shape == (4, 3, 2)
    if 2 in selected:
        assert block(moved, 2).shape == (4, 3, 1)
        assert block(jac[1][1], 2).shape == (2, 3, 1)  # SO3 of batch (2,) out, SO2 in
        assert block(jac[1][0], 2).shape == (1,)  # scalar out


def test_single_argnum_is_not_a_tuple():
    state, _, _, points = make_state()
    jac = lieax.jacobian(lambda s: s["pose"] @ points)(state)
    assert set(jac) == {"pose", "rotations", "bias"}
    assert jac["pose"].shape == (4, 3, 6) and jac["bias"].shape == (4, 3, 3)
    np.testing.assert_array_equal(jac["bias"], 0.0)


def test_grad_matches_jacobian_and_value():
    args = make_state()

    def cost(state, data, extra, points):
        return composite(state, data, extra, points)[1][0]

    @jax.jit
    def evaluate(args):
        return (
            lieax.value_and_grad(cost, (0, 1))(*args),
            lieax.jacobian(cost, (0, 1), mode="fwd")(*args),
            fd_dense(cost, args, (0, 1))(args),
        )

    (value, gradient), jac, expected = evaluate(args)
    np.testing.assert_allclose(value, cost(*args), rtol=1e-13)
    tree_allclose(gradient, jac)
    assert gradient[0]["pose"].shape == (6,) and gradient[0]["rotations"].shape == (2, 3)
    gradient_flat = np.concatenate([np.ravel(g) for g in jax.tree_util.tree_leaves(gradient)])
    assert_fd_close(gradient_flat[None, :], expected, "grad")


def test_has_aux_and_value_and_jacobian():
    args = make_state()

    def with_aux(state, data, extra, points):
        out, (cost, _) = composite(state, data, extra, points)
        return out["moved"], {"cost": cost, "count": 4}

    @jax.jit
    def evaluate(args):
        return (
            lieax.jacobian(with_aux, has_aux=True)(*args),
            lieax.jacobian(lambda *a: with_aux(*a)[0])(*args),
            lieax.value_and_jacobian(with_aux, has_aux=True)(*args),
            lieax.value_and_jacobian(composite, (0, 1, 2), mode="fwd")(*args),
        )

    (jac, aux), plain, ((value, aux2), jac2), (value3, jac3) = evaluate(args)
    tree_allclose(jac, plain)
    tree_allclose(jac2, plain)
    np.testing.assert_allclose(aux["cost"], composite(*args)[1][0], rtol=1e-13)
    assert int(aux["count"]) == int(aux2["count"]) == 4
    np.testing.assert_allclose(value, with_aux(*args)[0], rtol=1e-13)
    tree_allclose(value3, composite(*args))
    tree_allclose(jac3, composite_jacobians()[1])


def test_grad_passes_any_aux_through():
    x = element(SO3, 3)

    def scalar_with_aux(x):
        return jnp.sum(x.log()), "aux"

    (value, aux), gradient = lieax.value_and_grad(scalar_with_aux, has_aux=True)(x)
    gradient2, aux2 = lieax.grad(scalar_with_aux, has_aux=True)(x)
    assert aux == aux2 == "aux"
    np.testing.assert_allclose(gradient, gradient2, rtol=1e-14)
    np.testing.assert_allclose(value, jnp.sum(x.log()), rtol=1e-14)
    expected = np.asarray(SO3.right_jacobian_inverse(x.log())).T @ np.ones(3)
    np.testing.assert_allclose(gradient, expected, rtol=1e-12)


# ---- nested Jacobians, vmap ----------------------------------------------------------------------


@pytest.mark.parametrize(
    "G", [pytest.param(SE2, marks=pytest.mark.slow), SE3], ids=lambda G: G.__name__
)  # SE2's rules are the same generic code as SE3's
def test_jacobian_of_a_jacobian(G):
    """d/dX of `J(X, Y) = ∂ Log(X Y) / ∂X` (and of `∂ (X @ p) / ∂X`) against finite differences."""
    x, y = element(G, 6), element(G, 7)
    p = jnp.asarray(np.random.default_rng(8).normal(size=G.space_dim))

    def inner(x, y, p):
        log_jacobian = lieax.jacobian(lambda a: (a @ y).log())(x)
        act_jacobian = lieax.jacobian(lambda a, q: a @ q, (0, 1))(x, p)
        return log_jacobian, act_jacobian

    @jax.jit
    def evaluate(x, y, p):
        return (
            lieax.jacobian(inner, (0, 1, 2), mode="fwd")(x, y, p),
            lieax.jacobian(inner, (0, 1, 2), mode="rev")(x, y, p),
            fd_dense(inner, (x, y, p), (0, 1, 2))((x, y, p)),
        )

    outer, outer_rev, expected = evaluate(x, y, p)
    assert_fd_close(dense(outer, inner(x, y, p), [x, y, p]), expected, f"{G.__name__} nested")
    tree_allclose(outer_rev, outer, atol=1e-10)


def test_jacobian_under_vmap_and_of_a_batched_group():
    poses = element(SE3, 9, (5,))
    points = jnp.asarray(np.random.default_rng(9).normal(size=(5, 3)))

    def single(pose, point):
        return (pose @ point, pose.log())

    def total(poses):  # a function of the whole batch
        return jnp.sum(poses @ points, axis=0)

    @jax.jit
    def evaluate(poses, points):
        return (
            jax.vmap(lieax.jacobian(single, (0, 1)))(poses, points),
            lieax.jacobian(single, (0, 1))(poses, points),
            lieax.jacobian(total)(poses),
            [lieax.jacobian(single, (0, 1))(poses[i], points[i]) for i in range(5)],
        )

    vmapped, batched, jac_total, ones = evaluate(poses, points)
    assert jac_total.shape == (3, 5, 6)
    for i, one in enumerate(ones):
        tree_allclose(jax.tree_util.tree_map(lambda a, i=i: a[i], vmapped), one)
        tree_allclose(jax.tree_util.tree_map(lambda a, i=i: a[i, ..., i, :], batched), one)
        np.testing.assert_allclose(jac_total[:, i], one[0][0], atol=1e-12)


def test_jit_of_jacobian_equals_eager():
    x, y = element(SO3, 10), element(SO3, 11)
    f = lieax.jacobian(lambda a, b: a.between(b).log(), (0, 1))
    tree_allclose(jax.jit(f)(x, y), f(x, y))


# ---- gradients of Log at the identity and near π -------------------------------------------------


GRADIENT_POINTS = ["identity", "tiny", "small_rotation", "near_pi", "at_pi"]


def _gradient_point(spec, name):
    if name == "at_pi":
        xi = regime_tangent(spec, "near_pi")
        rotation = list(spec.rotation_index)
        xi[rotation] *= np.pi / np.linalg.norm(xi[rotation])
        return xi
    return regime_tangent(spec, name)


# Sim3's and SE23's logs go through `_generic.local_rules` as SE3's does (run by default), and
# test_jacobians.py checks their log's Jacobian at every regime, near π included: their cases
# (~25 s each) are slow.
@pytest.mark.parametrize(
    "spec",
    [
        pytest.param(s, id=s.name, marks=[pytest.mark.slow] if s.name in ("Sim3", "SE23") else [])
        for s in GROUPS
    ],
)
def test_gradient_of_log_is_finite(spec):
    """`jax.grad` (on the parameters), `jax.hessian` and `lieax.grad` of `w · Log(X)` are finite at
    the identity, 1e-9 from it, ~1e-4 rad, π - 1e-6 and at π; away from π, `lieax.grad` is
    `Jr⁻¹(Log X)ᵀ w`."""
    G = spec.cls
    xis = jnp.asarray(np.stack([_gradient_point(spec, name) for name in GRADIENT_POINTS]))
    weights = jnp.linspace(0.5, 1.5, spec.dim)

    def scalar(params):
        return jnp.dot(weights, G(params).log())

    @jax.jit
    def evaluate(xis):
        params = G.exp(xis).parameters()
        return (
            jax.vmap(jax.grad(scalar))(params),
            jax.vmap(jax.hessian(scalar))(params),
            jax.vmap(lieax.grad(lambda x: jnp.dot(weights, x.log())))(G.exp(xis)),
            G.right_jacobian_inverse(G.exp(xis).log()),
        )

    ambient, hessian, local, jr_inverse = (np.asarray(a) for a in evaluate(xis))
    for i, name in enumerate(GRADIENT_POINTS):
        assert np.all(np.isfinite(ambient[i])), f"{spec} jax.grad at {name}"
        assert np.all(np.isfinite(hessian[i])), f"{spec} jax.hessian at {name}"
        assert np.all(np.isfinite(local[i])), f"{spec} lieax.grad at {name}"
        if name != "at_pi":
            np.testing.assert_allclose(local[i], jr_inverse[i].T @ np.asarray(weights), atol=1e-9)


# ---- manifold helpers ----------------------------------------------------------------------------


def test_rplus_rminus_round_trip_on_trees():
    state, data, extra, _ = make_state()
    tree = {"state": state, "data": data, "extra": extra}
    zeros = lieax.zero_tangents(tree)
    assert zeros["state"]["pose"].shape == (6,)
    assert zeros["state"]["rotations"].shape == (2, 3)
    assert zeros["state"]["bias"].shape == (3,)
    assert zeros["data"][0].shape == (3,) and zeros["data"][1].shape == (2,)
    assert zeros["extra"].shape == (1,)
    assert all(z.dtype == jnp.float64 for z in jax.tree_util.tree_leaves(zeros))
    dim = lieax.tangent_dim(tree)
    assert dim == 6 + 6 + 3 + 3 + 2 + 1
    vector = jnp.asarray(np.random.default_rng(12).normal(size=dim)) * 0.5
    delta = lieax.unflatten_tangents(tree, vector)
    np.testing.assert_array_equal(lieax.flatten_tangents(delta), vector)
    moved = lieax.rplus(tree, delta)
    tree_allclose(lieax.rminus(moved, tree), delta)
    tree_allclose(lieax.rplus(tree, lieax.rminus(moved, tree)), moved)
    tree_allclose(lieax.rplus(tree, zeros), tree)
    # arrays move by addition
    np.testing.assert_allclose(moved["state"]["bias"], state["bias"] + delta["state"]["bias"])
    # groups move by X ⊕ δ
    np.testing.assert_allclose(
        moved["state"]["pose"].as_matrix(), state["pose"].rplus(delta["state"]["pose"]).as_matrix()
    )
    assert lieax.flatten_tangents(lieax.zero_tangents({})).shape == (0,)


def test_float32_trees_keep_their_dtype():
    tree = {"pose": SE3.identity(dtype=jnp.float32), "v": jnp.zeros(2, jnp.float32)}
    zeros = lieax.zero_tangents(tree)
    assert all(z.dtype == jnp.float32 for z in jax.tree_util.tree_leaves(zeros))

    def f(t):
        return t["pose"] @ jnp.ones(3, jnp.float32) + t["v"][0]

    for mode in ("fwd", "rev"):
        jac = jax.eval_shape(lieax.jacobian(f, mode=mode), tree)
        assert jac["pose"].dtype == jnp.float32 and jac["v"].dtype == jnp.float32


@pytest.mark.parametrize("mode", ["fwd", "rev"])
def test_jacobian_of_a_function_that_changes_dtype(mode):
    """A float32 input with a float64 output (issue 17: JAX's internal "tangent values
    inconsistent with the primal" error before): each leaf is seeded and read in its own dtype."""
    rotation = lieax.SO3.exp(jnp.array([0.1, -0.2, 0.3], jnp.float32))

    def widened_log(r, v):
        return lieax.SO3(r.parameters().astype(jnp.float64)).log() + v.astype(jnp.float64)

    J_r, J_v = lieax.jacobian(widened_log, argnums=(0, 1), mode=mode)(
        rotation, jnp.ones(3, jnp.float32)
    )
    assert J_r.dtype == J_v.dtype == jnp.float64
    reference = lieax.jacobian(lambda r: r.log(), mode=mode)(
        lieax.SO3(rotation.parameters().astype(jnp.float64))
    )
    np.testing.assert_allclose(J_r, reference, atol=1e-6)
    np.testing.assert_allclose(J_v, np.eye(3), atol=0)
