"""S2: the basis and the retraction against independent NumPy formulas, local Jacobians of its
operations against central finite differences (forward and reverse mode, batched and one element),
and S2 in `lieax.jacobian` and the solver.

Sim3's tests, once here, run from the registry (`tests/registry.py`) with every group's:
values and identities in `test_groups.py` (its constructors and the translation block by
quadrature there too), Jacobians over its regimes (scale included) in `test_jacobians.py`, second
derivatives and raw parameters in `test_second_order.py`, properties in `test_properties.py`.
The properties every manifold has (⊕ / ⊖ round trips, finite gradients, dtypes, broadcasting) run
for S2 from its registry entry (`test_properties.py`).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from registry import skew3 as skew

import lieax
import lieax.lstsq
from lieax.groups import _base
from lieax.groups._s2 import REFERENCE, S2, SWITCH

SO3 = lieax.SO3
MANIFOLD_PATCH = hasattr(_base, "AbstractManifold")
needs_manifold_patch = pytest.mark.skipif(
    not MANIFOLD_PATCH,
    reason="S2 as a lieax.jacobian / solver leaf needs AbstractManifold in _base.py (see _s2.py)",
)


def split_batched(block, count, out_size):
    """Per-element blocks `(count, out_size, in_size)` of a batched Jacobian block and the largest
    entry coupling different elements."""
    block = np.asarray(block).reshape(count, out_size, count, -1)
    diagonal = block[np.arange(count), :, np.arange(count), :]
    off = block.copy()
    off[np.arange(count), :, np.arange(count), :] = 0.0
    return diagonal, np.max(np.abs(off))


# ---- S2 ------------------------------------------------------------------------------------------

DIRECTIONS = np.array(
    [
        [0.0, 0.0, 1.0],
        [0.0, 0.0, -1.0],
        [1.0, 0.0, 0.0],
        [0.0, -1.0, 0.0],
        [0.3, -0.5, 0.81],
        [-0.6, 0.2, -0.7],
        [1.0, 1.0, 1.0],
        [-1.0, -1.0, -1.0],
        [0.2, 0.4, 0.6000001],  # near r = (1, 2, 3)/√14, where the basis is the reference frame
        list(-np.asarray(REFERENCE) + np.array([1e-2, -2e-2, 0.0])),  # ~0.02 from -r (second chart)
    ]
)
DIRECTIONS = DIRECTIONS / np.linalg.norm(DIRECTIONS, axis=1, keepdims=True)


_R = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)
_U1 = np.array([-2.0, 1.0, 0.0]) / np.sqrt(5.0)
_U = np.stack([_U1, np.cross(_R, _U1)], axis=1)


def s2_basis_np(p):
    r"""The documented basis, written independently: the minimal rotation taking r to p applied to
    the reference frame, $R = I + [k]_\times + [k]_\times^2 / (1 + r^\top p)$, $k = r \times p$;
    within the switching circle ($1 + r^\top p <$ `SWITCH`) the same from $-r$ and $[u_1, -u_2]$."""
    p = p / np.linalg.norm(p)
    r, frame = (_R, _U) if 1.0 + _R @ p >= SWITCH else (-_R, _U * np.array([1.0, -1.0]))
    k = skew(np.cross(r, p))
    return (np.eye(3) + k + k @ k / (1.0 + r @ p)) @ frame


def s2_plus(p, xi):
    u = p + s2_basis_np(p) @ xi
    return u / np.linalg.norm(u)


def s2_minus(q, p):
    return s2_basis_np(p).T @ q / (p @ q)


def test_s2_basis_and_retraction():
    """The basis: the documented formula, orthonormal, tangent, smooth away from the switching
    circle, finite at -r; the retraction round trip; agreement with the exponential map to third
    order; zero error at coincident directions."""
    rng = np.random.default_rng(5)
    xi = rng.normal(size=(len(DIRECTIONS), 2))

    @jax.jit
    def evaluate(ps, xi, antipode):
        p = S2(ps)
        q = p.rplus(xi)
        small = p.rplus(1e-3 * xi)
        return {
            "basis": p.basis(),
            "q": q.unit_vector(),
            "back": q.rminus(p),
            "again": p.rplus(q.rminus(p)).unit_vector(),
            "same": p.rplus(jnp.zeros_like(xi)).unit_vector(),
            "small_angle": p.distance(small),
            "self_error": p.error(p),
            "antipode": S2(antipode).basis(),
            "antipode_gradient": jax.grad(lambda v: jnp.sum(S2(v).basis() ** 2))(antipode),
            "from_vector": S2.from_vector(jnp.array([0.0, 3.0, 4.0])).unit_vector(),
        }

    out = jax.tree_util.tree_map(
        np.asarray,
        evaluate(jnp.asarray(DIRECTIONS), jnp.asarray(xi), -jnp.asarray(REFERENCE)),
    )
    b = out["basis"]
    for direction, basis in zip(DIRECTIONS, b):
        np.testing.assert_allclose(basis, s2_basis_np(direction), atol=1e-14)
    np.testing.assert_allclose(
        np.swapaxes(b, -1, -2) @ b, np.broadcast_to(np.eye(2), (len(b), 2, 2)), atol=1e-14
    )
    np.testing.assert_allclose(np.einsum("nij,ni->nj", b, DIRECTIONS), 0.0, atol=1e-14)
    for direction in DIRECTIONS:
        for step in (np.array([1e-6, 0.0]), np.array([0.0, -1e-6])):
            assert (
                np.max(np.abs(s2_basis_np(s2_plus(direction, step)) - s2_basis_np(direction)))
                < 1e-4
            )
    assert np.all(np.isfinite(out["antipode"])) and np.all(np.isfinite(out["antipode_gradient"]))
    np.testing.assert_allclose(out["antipode"].T @ out["antipode"], np.eye(2), atol=1e-14)
    np.testing.assert_allclose(out["antipode"].T @ np.asarray(REFERENCE), 0.0, atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(out["q"], axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(out["back"], xi, atol=1e-12)
    np.testing.assert_allclose(out["again"], out["q"], atol=1e-14)
    np.testing.assert_allclose(out["same"], DIRECTIONS, atol=1e-16)
    np.testing.assert_allclose(
        out["small_angle"], np.arctan(np.linalg.norm(1e-3 * xi, axis=-1)), atol=1e-15
    )
    np.testing.assert_allclose(out["self_error"], 0.0, atol=1e-14)
    np.testing.assert_allclose(out["from_vector"], [0.0, 0.6, 0.8], atol=1e-16)


def _s2_fd(f, args, kinds, output, step=1e-6):
    """Central differences in local coordinates: S2 arguments moved by the retraction, SO3 by
    `R·Exp`, arrays by addition; S2 outputs compared by `⊖` at the base value."""
    base = f(*args)
    blocks = []
    for i, kind in enumerate(kinds):
        size = {"s2": 2, "so3": 3}.get(kind, np.size(args[i]))
        columns = []
        for e in np.eye(size):
            sides = []
            for sign in (1.0, -1.0):
                moved = list(args)
                if kind == "s2":
                    moved[i] = s2_plus(args[i], sign * step * e)
                elif kind == "so3":
                    moved[i] = args[i] @ scipy.linalg.expm(skew(sign * step * e))
                else:
                    moved[i] = args[i] + sign * step * e
                value = f(*moved)
                sides.append(s2_minus(value, base) if output == "s2" else np.ravel(value - base))
            columns.append((sides[0] - sides[1]) / (2 * step))
        blocks.append(np.stack(columns, axis=1))
    return blocks


@needs_manifold_patch
def test_s2_jacobians():
    r"""lieax.jacobian (fwd and rev, batched and one element) of rplus, rminus, rotate, error and
    distance against finite differences; rotate against the notes' closed form
    $[-B_{Rp}^\top R[p]_\times, B_{Rp}^\top R B_p]$ and error's $\partial/\partial q = B_p^\top B_q$."""
    rng = np.random.default_rng(11)
    count = len(DIRECTIONS)
    ps = DIRECTIONS
    qs = np.stack([s2_plus(p, 0.4 * rng.normal(size=2)) for p in ps])
    xis = 0.7 * rng.normal(size=(count, 2))
    rotations = np.stack([scipy.linalg.expm(skew(w)) for w in rng.normal(size=(count, 3))])
    rotation_params = SO3.from_matrix(jnp.asarray(rotations))
    cases = {
        "rplus": (
            lambda p, xi: p.rplus(xi),
            (S2(jnp.asarray(ps)), jnp.asarray(xis)),
            lambda p, xi: s2_plus(p, xi),
            (ps, xis),
            ("s2", "vec"),
            "s2",
        ),
        "rminus": (
            lambda q, p: q.rminus(p),
            (S2(jnp.asarray(qs)), S2(jnp.asarray(ps))),
            s2_minus,
            (qs, ps),
            ("s2", "s2"),
            "vec",
        ),
        "rotate": (
            lambda r, p: p.rotate(r),
            (rotation_params, S2(jnp.asarray(ps))),
            lambda r, p: r @ p,
            (rotations, ps),
            ("so3", "s2"),
            "s2",
        ),
        "error": (
            lambda p, q: p.error(q),
            (S2(jnp.asarray(ps)), S2(jnp.asarray(qs))),
            lambda p, q: s2_basis_np(p).T @ q,
            (ps, qs),
            ("s2", "s2"),
            "vec",
        ),
        "distance": (
            lambda p, q: p.distance(q),
            (S2(jnp.asarray(ps)), S2(jnp.asarray(qs))),
            lambda p, q: np.arctan2(np.linalg.norm(np.cross(p, q)), p @ q),
            (ps, qs),
            ("s2", "s2"),
            "vec",
        ),
    }
    out_sizes = {"rplus": 2, "rminus": 2, "rotate": 2, "error": 2, "distance": 1}

    def evaluate(all_args):
        out = {  # reverse mode where the S2 carrier maps are transposed on both sides
            name: (
                lieax.jacobian(case[0], (0, 1), mode="fwd")(*all_args[name]),
                lieax.jacobian(case[0], (0, 1), mode="rev")(*all_args[name])
                if name in ("rotate", "rminus")
                else None,
            )
            for name, case in cases.items()
        }
        p = all_args["error"][0]
        out["at_zero"] = lieax.jacobian(lambda xi, p: p.rplus(xi))(jnp.zeros((count, 2)), p)
        out["coincident"] = (
            lieax.jacobian(lambda a: a.distance(p))(p),
            lieax.jacobian(lambda a: jnp.sum(a.error(p)))(p),
        )
        rotation, direction = all_args["rotate"][0][4], all_args["rotate"][1][4]
        out["single"] = lieax.jacobian(cases["rotate"][0], (0, 1))(rotation, direction)
        return out

    jacobians = jax.jit(evaluate)({name: case[1] for name, case in cases.items()})
    for name, (_f, _args, reference, np_args, kinds, output) in cases.items():
        fwd, rev = jacobians[name]
        for position in range(2):
            if rev is not None:
                np.testing.assert_allclose(rev[position], fwd[position], atol=1e-12, err_msg=name)
            blocks, off = split_batched(fwd[position], count, out_sizes[name])
            assert off == 0.0, name
            for index in range(count):
                element = [a[index] for a in np_args]
                expected = _s2_fd(reference, element, kinds, output)[position]
                error = np.max(np.abs(blocks[index] - expected))
                assert error < 1e-7 * max(1.0, np.abs(expected).max()), (
                    f"S2 {name} d/d(arg {position}) at {ps[index]}: {error:.3g}\n{blocks[index]}\n{expected}"
                )
        if name == "rotate":
            for index in range(count):
                r, p = rotations[index], ps[index]
                b_out, b_in = s2_basis_np(r @ p), s2_basis_np(p)
                closed = (-b_out.T @ r @ skew(p), b_out.T @ r @ b_in)
                for position in range(2):
                    blocks, _ = split_batched(fwd[position], count, 2)
                    np.testing.assert_allclose(blocks[index], closed[position], atol=1e-14)
        if name == "error":
            blocks, _ = split_batched(fwd[1], count, 2)
            for index in range(count):
                np.testing.assert_allclose(
                    blocks[index], s2_basis_np(ps[index]).T @ s2_basis_np(qs[index]), atol=1e-14
                )
    # one element without batch axes gives the same block
    for position in range(2):
        np.testing.assert_allclose(
            jacobians["single"][position],
            split_batched(jacobians["rotate"][0][position], count, 2)[0][4],
            atol=1e-14,
        )
    # the derivative of the retraction at 0 is the identity in local coordinates
    np.testing.assert_allclose(
        split_batched(jacobians["at_zero"], count, 2)[0],
        np.broadcast_to(np.eye(2), (count, 2, 2)),
        atol=1e-14,
    )
    # NaN-free at coincident directions
    for jac in jacobians["coincident"]:
        assert np.all(np.isfinite(jac))


@needs_manifold_patch
def test_s2_in_solver_and_tree_helpers():
    """Estimate an unknown direction from rotated observations with the Levenberg-Marquardt solver,
    with the state a pytree mixing S2 and an array."""
    rng = np.random.default_rng(3)
    truth = np.array([0.2, -0.6, 0.77])
    truth /= np.linalg.norm(truth)
    rotations = SO3.exp(jnp.asarray(rng.normal(size=(20, 3))))
    observed = S2(rotations.act(jnp.asarray(truth)))
    offset_truth = jnp.array([0.5, -1.0])

    def residual(state, data):
        direction, offset = state
        rotations, observed = data
        predicted = direction.rotate(rotations)
        return observed.error(predicted), offset - offset_truth

    x0 = (S2.from_vector(jnp.array([0.0, 0.0, 1.0])), jnp.zeros(2))
    solution = lieax.lstsq.least_squares(residual, x0, (rotations, observed))
    direction, offset = solution.value
    np.testing.assert_allclose(direction.unit_vector(), truth, atol=1e-9)
    np.testing.assert_allclose(offset, offset_truth, atol=1e-9)
    assert lieax.tangent_dim(x0) == 4
    moved = lieax.rplus(x0, (jnp.array([0.1, 0.2]), jnp.ones(2)))
    np.testing.assert_allclose(lieax.rminus(moved, x0)[0], [0.1, 0.2], atol=1e-14)
    gradient = lieax.grad(lambda s: jnp.sum(s.unit_vector() * jnp.array([1.0, 2.0, 3.0])))(x0[0])
    assert gradient.shape == (2,)
