"""ICP invariance and reliability: registering clouds moved far from the origin (georeferenced
scans) and rotated gives the result at the origin, conjugated; parameters out of range and
non-finite input give clear errors eagerly and a status under `jit` / `vmap`; the float32 point
transform agrees with float64 at 20k points.

Every call registers the same 400-point pair (one compiled loop per kind and dtype).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lieax import SE3, icp
from lieax.icp import _coordinates, _host_kdtree
from lieax.lstsq import Huber

RADIUS = 0.2
OFFSET_DIRECTION = np.array([1.0, -0.7, 0.3])  # (1e4, -7e3, 3e3) m at 1e4 m: UTM-like
KINDS = ("point_to_plane", "point_to_point", "gicp")


@pytest.fixture(scope="module")
def pair():
    return icp.synthetic_pair(400, rotation_deg=3.0, translation=0.05, noise=0.001, seed=4)


def placement(offset, rotated, dtype=jnp.float64):
    """`G = (Q, offset · OFFSET_DIRECTION)` with a random rotation `Q` (or the identity)."""
    angle = np.random.default_rng(11).normal(size=3) if rotated else np.zeros(3)
    return SE3.exp(jnp.asarray(np.concatenate([offset * OFFSET_DIRECTION, angle]), dtype))


def register(kind, pair, G, dtype=jnp.float64, **options):
    """Register the pair with both clouds (and the normals) moved by `G`."""
    source, target, normals, _ = pair
    source, target = (G @ source).astype(dtype), (G @ target).astype(dtype)
    if kind == "point_to_plane":
        options.setdefault("target_normals", (G.rotation() @ normals).astype(dtype))
    options.setdefault("init", SE3.identity(dtype=dtype))  # (every call shares a compiled loop)
    method = getattr(icp, kind)
    return method(source, target, max_correspondence_distance=RADIUS, throw=False, **options)


def relative_error(result, G, reference):
    """(translation, rotation) of `reference⁻¹ · G⁻¹ T G`: how far the result, moved back by `G`,
    lies from the result at the origin."""
    T = SE3._wrap(result.transform.parameters().astype(jnp.float64))
    G = SE3._wrap(G.parameters().astype(jnp.float64))
    xi = np.asarray(reference.inverse().compose(G.inverse() @ T @ G).log())
    return float(np.linalg.norm(xi[:3])), float(np.linalg.norm(xi[3:]))


@pytest.fixture(scope="module")
def at_origin(pair):
    return {kind: register(kind, pair, placement(0.0, False)) for kind in KINDS}


# ---- placement ----------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_result_does_not_depend_on_placement(pair, at_origin, kind):
    """Both clouds moved 1e4-1e6 m and rotated: the same status and iterations, and the pose
    within 10 ulps of the coordinates of the result at the origin. (Solved about the origin, 1e4
    m ended MAX_ITERATIONS 2 cm and 2.8° off, and 1e5 m CONVERGED without having moved.)"""
    reference = at_origin[kind]
    assert reference.status_name == "CONVERGED"
    truth = pair[3]
    assert relative_error(reference, placement(0.0, False), truth)[0] < 1e-3
    for offset in (0.0, 1e4, 1e5, 1e6):
        G = placement(offset, rotated=True)
        result = register(kind, pair, G)
        assert result.status_name == "CONVERGED", offset
        assert int(result.iterations) == int(reference.iterations), offset
        assert float(result.fitness) == float(reference.fitness)
        translation, rotation = relative_error(result, G, reference.transform)
        tolerance = 1e-12 + 10 * np.spacing(offset)
        assert translation < tolerance and rotation < tolerance, (offset, translation, rotation)
        np.testing.assert_allclose(float(result.inlier_rmse), float(reference.inlier_rmse),
                                   rtol=1e-6)  # fmt: skip


@pytest.mark.parametrize("kind", ["point_to_point"])  # (the least precise in float32)
def test_float32_placement(pair, at_origin, kind):
    """What float32 can do: coordinates at a distance L are rounded to ulp(L) (1 mm at 1e4 m,
    8 mm at 1e5 m), which bounds the rotation (measured: 0.01-0.05 ulp(L) rad, as float64 on the
    rounded clouds); and a float32 rotation of `T_target_source`, good to a few ε, moves the clouds
    by a few ε·L = ulp(L) (measured: 0.5-5 ulps). Asserted: 8 ulps(L) and 0.1 ulp(L) rad of the
    float64 result at the origin, with its status and iterations."""
    reference = at_origin[kind].transform
    for offset in (1e3, 1e4):
        G = placement(offset, rotated=True)
        result = register(kind, pair, G, dtype=jnp.float32)
        assert result.transform.parameters().dtype == jnp.float32
        assert result.status_name == "CONVERGED"
        assert int(result.iterations) == int(at_origin[kind].iterations)
        ulp = float(np.spacing(np.float32(offset * np.linalg.norm(OFFSET_DIRECTION))))
        translation, rotation = relative_error(result, G, reference)
        assert translation < 8 * ulp and rotation < 0.1 * ulp, (offset, translation, rotation)


def test_multi_scale_placement(pair):
    """The voxel grids are anchored at the clouds (translation invariant): a level on voxel
    centroids gives the result at the origin, 1e5 m away."""
    source, target, _, _ = pair
    options = dict(voxel_sizes=(0.1,), max_correspondence_distances=(0.4,),
                   method="point_to_point", max_iterations=np.int64(30))  # fmt: skip
    reference = icp.multi_scale(source, target, **options)
    offset = jnp.asarray(1e5 * OFFSET_DIRECTION)
    result = icp.multi_scale(source + offset, target + offset, **options)
    assert result.status_name == reference.status_name == "CONVERGED"
    G = placement(1e5, False)
    translation, rotation = relative_error(result, G, reference.transform)
    assert translation < 1e-9 and rotation < 1e-9


def test_prebuilt_index_far_from_the_origin(pair, at_origin):
    """An index prebuilt on the target as given (1e5 m away): the loop queries it in the target's
    frame, so the result is that of the origin. (Every index gets the same shifted queries.)"""
    G = placement(1e5, rotated=True)
    index = icp.build_index(G @ pair[1], search="kdtree")
    result = register("point_to_plane", pair, G, search=index)
    assert result.status_name == "CONVERGED"
    translation, rotation = relative_error(result, G, at_origin["point_to_plane"].transform)
    assert translation < 1e-9 and rotation < 1e-9


def test_buckets_and_the_host_tree_far_from_the_origin(pair):
    """Padding to the capacity bucket (400 -> 448 rows) gives the unpadded result at 1e5 m; the
    loop builds its k-d tree on the target as given, so with the host tree (no native library) a
    tree prebuilt on the same points is found in the registry (no second tree; the native tree
    keeps no registry)."""
    G = placement(1e5, rotated=True)
    icp.build_index(G @ pair[1], search="kdtree")
    trees = len(_host_kdtree._TREES)
    exact = register("point_to_plane", pair, G, buckets=False, search="kdtree")
    assert len(_host_kdtree._TREES) == trees
    padded = register("point_to_plane", pair, G, buckets=True, search="kdtree")
    assert exact.status_name == padded.status_name == "CONVERGED"
    np.testing.assert_allclose(np.asarray(padded.transform.parameters()),
                               np.asarray(exact.transform.parameters()), rtol=0, atol=1e-9)  # fmt: skip
    np.testing.assert_array_equal(
        np.asarray(padded.correspondences), np.asarray(exact.correspondences)
    )


def test_derivatives_do_not_depend_on_placement(pair):
    """The implicit derivative of the pose relative to the clouds is the same 1e5 m away
    (its 6x6 system is solved about the centroids too)."""
    source, target, normals, _ = pair
    rng = np.random.default_rng(2)
    source_dot, target_dot = (jnp.asarray(rng.normal(size=source.shape)) for _ in range(2))

    def relative(offset):
        G = placement(offset, rotated=True)

        def pose(s, t):
            result = icp.point_to_plane(
                G @ s, G @ t, target_normals=G.rotation() @ normals,
                max_correspondence_distance=RADIUS, relative_fitness=1e-12, relative_rmse=1e-12,
            )  # fmt: skip
            return (G.inverse() @ result.transform @ G).parameters(), result.inlier_rmse

        return jax.jvp(pose, (source, target), (source_dot, target_dot))[1]

    (pose_dot, rmse_dot), (far_pose_dot, far_rmse_dot) = relative(0.0), relative(1e5)
    assert np.all(np.isfinite(np.asarray(pose_dot))) and np.linalg.norm(pose_dot) > 1e-3
    np.testing.assert_allclose(np.asarray(far_pose_dot), np.asarray(pose_dot), atol=1e-8)
    np.testing.assert_allclose(float(far_rmse_dot), float(rmse_dot), atol=1e-8)


# ---- parameters ---------------------------------------------------------------------------------


def test_multi_scale_nonfinite_input(pair):
    """A NaN source point, dropped by the voxel level, still makes the result NONFINITE (with
    `init`, zero iterations), and raises with `throw=True`."""
    source, target, _, _ = pair
    options = dict(voxel_sizes=(0.1,), max_correspondence_distances=(0.4,),
                   method="point_to_point", max_iterations=np.int64(30))  # fmt: skip
    broken = source.at[17, 1].set(jnp.nan)
    result = icp.multi_scale(broken, target, throw=False, **options)
    assert result.status_name == "NONFINITE" and int(result.iterations) == 0
    np.testing.assert_array_equal(np.asarray(result.transform.parameters()),
                                  np.asarray(SE3.identity().parameters()))  # fmt: skip
    with pytest.raises(icp.ICPInputError, match="NONFINITE"):
        icp.multi_scale(source, target.at[3, 0].set(jnp.inf), **options)


@pytest.mark.parametrize(
    "options, message",
    [
        ({"max_correspondence_distance": jnp.array(-1.0)}, "max_correspondence_distance must be"),
        ({"max_correspondence_distance": np.float32(0.0)}, "max_correspondence_distance must be"),
        ({"max_correspondence_distance": jnp.array(np.inf)}, "max_correspondence_distance must"),
        ({"max_correspondence_distance": jnp.ones(2)}, "max_correspondence_distance must be a"),
        ({"relative_fitness": jnp.array(-1e-6)}, "relative_fitness must be non-negative"),
        ({"relative_rmse": np.nan}, "relative_rmse must be non-negative and finite"),
        ({"max_iterations": 3.0}, "max_iterations must be an int"),
        ({"max_iterations": np.int64(-1)}, "max_iterations must be an int of at least 0"),
        ({"loss": Huber._unchecked(jnp.array(-0.1))}, "the scale of Huber must be positive"),
    ],
)
def test_concrete_parameters_are_checked(pair, options, message):
    source, target, _, _ = pair
    options = {"max_correspondence_distance": RADIUS, **options}
    with pytest.raises(icp.ICPInputError, match=message) as caught:
        icp.point_to_point(source, target, **options)
    assert isinstance(caught.value, ValueError)


def test_numpy_integers_are_accepted(pair, at_origin):
    source, target, _, _ = pair
    result = icp.point_to_point(source, target, max_correspondence_distance=RADIUS,
                                max_iterations=np.int64(30), init=SE3.identity())  # fmt: skip
    np.testing.assert_allclose(
        np.asarray(result.transform.parameters()),
        np.asarray(at_origin["point_to_point"].transform.parameters()),
        atol=1e-9,
    )
    few = target[:16]
    assert icp.voxel_downsample(few, np.float64(0.1), size=np.int64(8))[0].shape == (8, 3)
    with pytest.raises(icp.ICPInputError, match="voxel_size must be positive"):
        icp.voxel_downsample(few, jnp.array(-0.1))


# ---- non-finite input ---------------------------------------------------------------------------


def test_nonfinite_input_returns_init(pair):
    """A non-finite `init`, source, target or normal: status NONFINITE, `init` unchanged (NaN
    for a NaN `init`), zero iterations; eagerly with `throw=True` an `ICPInputError`."""
    source, target, normals, _ = pair
    init = SE3.exp(jnp.array([0.01, 0.0, 0.0, 0.0, 0.0, 0.02]))
    nan_init = SE3._wrap(init.parameters().at[4].set(jnp.nan))
    cases = {
        "init": dict(init=nan_init),
        "source": dict(source=source.at[3, 1].set(jnp.inf)),
        "target": dict(target=target.at[9, 0].set(jnp.nan)),
        "normals": dict(target_normals=normals.at[5, 2].set(jnp.nan)),
    }
    for what, case in cases.items():
        options = dict(source=source, target=target, target_normals=normals, init=init)
        options.update(case)
        result = icp.point_to_plane(max_correspondence_distance=RADIUS, throw=False, **options)
        assert result.status_name == "NONFINITE", what
        assert int(result.iterations) == 0 and float(result.fitness) == 0.0
        np.testing.assert_array_equal(
            np.asarray(result.transform.parameters()), np.asarray(options["init"].parameters())
        )
        with pytest.raises(icp.ICPInputError, match="not finite"):
            icp.point_to_plane(max_correspondence_distance=RADIUS, **options)


def test_bad_problems_in_a_batch_disturb_no_other(pair):
    """Under `vmap`, traced parameters out of range (a non-positive or NaN distance, a negative
    tolerance, a zero loss scale) end their problem INVALID, and a NaN `init` or target point
    NONFINITE, each with `init` unchanged and zero iterations; the good problem is unchanged."""
    source, target, normals, _ = pair
    init = SE3.exp(jnp.array([0.01, 0.0, 0.0, 0.0, 0.0, 0.02])).parameters()
    good = (RADIUS, 1e-6, 10.0, init, target)
    bad = [
        (-RADIUS, 1e-6, 10.0, init, target),
        (jnp.nan, 1e-6, 10.0, init, target),
        (RADIUS, -1.0, 10.0, init, target),
        (RADIUS, 1e-6, 0.0, init, target),
        (RADIUS, 1e-6, 10.0, init.at[5].set(jnp.nan), target),
        (RADIUS, 1e-6, 10.0, init, target.at[2, 0].set(jnp.nan)),
    ]
    stacked = [jnp.stack([jnp.asarray(x) for x in column]) for column in zip(good, *bad)]

    @jax.vmap
    def batch(distance, tolerance, scale, init, target):
        return icp.point_to_plane(
            source, target, target_normals=normals, max_correspondence_distance=distance,
            relative_rmse=tolerance, loss=Huber._unchecked(scale), init=SE3._wrap(init),
            throw=False,
        )  # fmt: skip

    results = batch(*stacked)
    assert list(results.status_name) == ["CONVERGED"] + ["INVALID"] * 4 + ["NONFINITE"] * 2
    np.testing.assert_array_equal(np.asarray(results.iterations)[1:], 0)
    np.testing.assert_array_equal(np.asarray(results.transform.parameters())[1:], stacked[3][1:])
    single = icp.point_to_plane(source, target, target_normals=normals, loss=Huber(10.0),
                                init=SE3._wrap(init), max_correspondence_distance=RADIUS)  # fmt: skip
    np.testing.assert_allclose(np.asarray(results.transform.parameters()[0]),
                               np.asarray(single.transform.parameters()), atol=1e-9)  # fmt: skip


# ---- the float32 point transform ----------------------------------------------------------------


def test_float32_transform_of_20k_points_matches_float64():
    """`transform_points` (the loop's) and `SE3.act` in float32 on 20k points agree with float64
    in every row (a float32 miscompile of `SE3.act` from row 10922 on was once claimed)."""
    rng = np.random.default_rng(0)
    points = rng.normal(size=(20_000, 3))
    pose = SE3.exp(jnp.asarray(rng.normal(size=6)))
    expected = np.asarray(pose @ jnp.asarray(points))
    pose32 = SE3._wrap(pose.parameters().astype(jnp.float32))
    points32 = jnp.asarray(points, jnp.float32)
    for moved in (
        jax.jit(_coordinates.transform_points)(pose32.parameters(), points32),
        jax.jit(lambda T, p: T @ p)(pose32, points32),
    ):
        assert moved.dtype == jnp.float32
        np.testing.assert_allclose(np.asarray(moved), expected, rtol=0, atol=1e-5)
