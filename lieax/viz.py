"""Matplotlib drawings for notebooks and examples: frames as axes triads, point clouds, 2D and 3D
pose graphs, and cost curves.

matplotlib is an optional dependency (the `examples` and `notebooks` extras): it is imported
inside each function, so `import lieax.viz` costs nothing without it. Every function draws into
the axes it is given (`ax=`), or into new axes of a new pyplot figure, and returns the axes.
Arrays may be JAX or NumPy arrays; they are copied to the host.

Frames follow lieax's conventions (docs/conventions.md): a pose `T_world_body` is drawn at
its translation, with its rotation's columns (the body axes expressed in the world frame) as the
x, y, z axes in red, green and blue.
"""

from collections.abc import Iterable
from typing import TYPE_CHECKING, Protocol

import numpy as np
from jax.typing import ArrayLike

from .groups import SE3, AbstractGroup

if TYPE_CHECKING:  # matplotlib is optional: imported inside the functions that draw
    from matplotlib.axes import Axes
    from matplotlib.typing import ColorType

    from .graph import PoseGraph

__all__ = [
    "plot_cost",
    "plot_frames",
    "plot_points",
    "plot_pose_graph",
    "plot_registration",
    "set_axes_equal",
]

AXIS_COLORS = ("tab:red", "tab:green", "tab:blue")


class _CostHistory(Protocol):
    """A result with a cost history (`lieax.lstsq.Solution`, `lieax.graph.OptimizeResult`)."""

    @property
    def cost_history(self) -> ArrayLike: ...


# ---- helpers ----------------------------------------------------------------------------------


def _pyplot():
    try:
        import matplotlib.pyplot as plt
    except ImportError as error:  # pragma: no cover - depends on the environment
        raise ImportError(
            "lieax.viz needs matplotlib: pip install 'lieax[notebooks]' (or 'lieax[examples]')."
        ) from error
    return plt


def _axes(ax, dim, figsize=None):
    """`ax`, or new axes (3D when `dim == 3`) on a new figure."""
    if ax is not None:
        if dim == 3 and getattr(ax, "name", "") != "3d":
            raise ValueError("3D data needs 3D axes: fig.add_subplot(projection='3d').")
        return ax
    plt = _pyplot()
    fig = plt.figure(figsize=figsize)
    return fig.add_subplot(projection="3d" if dim == 3 else None)


def _segments(starts, ends):
    """Line segments `starts[k] -> ends[k]` as one NaN-separated polyline (one `plot` call)."""
    starts, ends = np.asarray(starts, float), np.asarray(ends, float)
    gap = np.full_like(starts, np.nan)
    return np.stack([starts, ends, gap], axis=1).reshape(-1, starts.shape[-1])


def set_axes_equal(ax: "Axes") -> "Axes":
    """Equal scale on every axis: 2D axes get an equal aspect; 3D axes get a cube around all the
    data drawn so far (call it again after adding data)."""
    if getattr(ax, "name", "") != "3d":
        shared = any(
            len(group.get_siblings(ax)) > 1
            for group in (ax.get_shared_x_axes(), ax.get_shared_y_axes())
        )
        ax.set_aspect("equal", adjustable="box" if shared else "datalim")
        return ax
    limits = np.array([ax.xy_dataLim.intervalx, ax.xy_dataLim.intervaly, ax.zz_dataLim.intervalx])
    if not np.all(np.isfinite(limits)):
        return ax
    centre = limits.mean(axis=1)
    radius = max(0.5 * float(np.max(limits[:, 1] - limits[:, 0])), 1e-9)
    ax.set_xlim3d(centre[0] - radius, centre[0] + radius)
    ax.set_ylim3d(centre[1] - radius, centre[1] + radius)
    ax.set_zlim3d(centre[2] - radius, centre[2] + radius)
    ax.set_box_aspect((1.0, 1.0, 1.0))
    return ax


def _rotations_and_positions(frames, positions):
    """`(R (k, d, d), t (k, d))` from a batch of lieax group elements: SE2/SE3 (and Sim3) give
    their rotation (scaled) and translation, SO2/SO3 their rotation at `positions` (default the
    origin)."""
    matrix = np.asarray(frames.as_matrix(), dtype=float)
    d = frames.space_dim
    matrix = matrix.reshape(-1, *matrix.shape[-2:])
    if matrix.shape[-1] == d + 1:  # homogeneous: [R t; 0 1]
        rotation, translation = matrix[:, :d, :d], matrix[:, :d, d]
    else:
        rotation, translation = matrix, np.zeros((matrix.shape[0], d))
    if positions is not None:
        translation = np.broadcast_to(
            np.asarray(positions, float).reshape(-1, d), translation.shape
        )
    return rotation, translation


# ---- frames -----------------------------------------------------------------------------------


def plot_frames(
    frames: AbstractGroup,
    *,
    ax: "Axes | None" = None,
    length: float | None = None,
    positions: ArrayLike | None = None,
    linewidth: float = 1.5,
    alpha: float = 1.0,
    origin_color: "ColorType | None" = None,
    labels: Iterable[object] | None = None,
    equal: bool = True,
) -> "Axes":
    """Draw each element of a batch of poses (`SE2`, `SE3`) or rotations (`SO2`, `SO3`) as a
    triad of axes: x red, y green (and z blue in 3D), from the frame's origin.

    **Arguments:**

    - `frames`: a lieax group element of any batch shape (`T_world_frame`).
    - `ax`: matplotlib axes (3D axes for 3D groups); new axes when `None`.
    - `length`: axis length; default a tenth of the spread of the origins (1 for a single frame).
    - `positions`: `(k, d)` origins for rotations (default the world origin).
    - `origin_color`: mark each origin with a dot of this colour (`None`: no dot).
    - `labels`: one text per frame, written at its origin.
    - `equal`: set equal axis scales.

    **Returns:** the axes.
    """
    rotation, origin = _rotations_and_positions(frames, positions)
    d = origin.shape[1]
    ax = _axes(ax, d)
    if length is None:
        spread = float(np.max(np.ptp(origin, axis=0))) if len(origin) > 1 else 0.0
        length = 0.1 * spread if spread > 0 else 1.0
    for k in range(d):
        tips = origin + length * rotation[:, :, k]
        ax.plot(*_segments(origin, tips).T, color=AXIS_COLORS[k], linewidth=linewidth, alpha=alpha)
    if origin_color is not None:
        ax.plot(*origin.T, ".", color=origin_color, markersize=4)
    if labels is not None:
        for text, point in zip(labels, origin):
            ax.text(*point, f" {text}")
    if equal:
        set_axes_equal(ax)
    return ax


# ---- point clouds -----------------------------------------------------------------------------


def _subsample(points, max_points, seed, mask=None):
    points = np.asarray(points, dtype=float).reshape(-1, np.shape(points)[-1])
    if mask is not None:
        points = points[np.asarray(mask, bool).reshape(-1)]
    if max_points is not None and len(points) > max_points:
        keep = np.random.default_rng(seed).choice(len(points), max_points, replace=False)
        points = points[np.sort(keep)]
    return points


def plot_points(
    points: ArrayLike,
    *,
    ax: "Axes | None" = None,
    max_points: int | None = 5000,
    mask: ArrayLike | None = None,
    seed: int = 0,
    size: float = 1.0,
    color: "ColorType | None" = None,
    alpha: float = 0.8,
    label: str | None = None,
    equal: bool = True,
) -> "Axes":
    """Scatter a point cloud `(n, 3)` in 3D (or `(n, 2)` in 2D), randomly subsampled to at most
    `max_points` points (reproducibly, from `seed`; `None` keeps all). `mask` drops padded rows
    (`False`), as `lieax.icp.pad_clouds` makes them.

    **Returns:** the axes.
    """
    points = _subsample(points, max_points, seed, mask)
    d = points.shape[1]
    if d not in (2, 3):
        raise ValueError(f"points must have shape (n, 2) or (n, 3), got {points.shape}.")
    ax = _axes(ax, d)
    if d == 3:
        ax.scatter(*points.T, s=size, c=color, alpha=alpha, label=label, depthshade=False)
    else:
        ax.scatter(*points.T, s=size, c=color, alpha=alpha, label=label)
    if equal:
        set_axes_equal(ax)
    return ax


def plot_registration(
    source: ArrayLike,
    target: ArrayLike,
    transform: SE3 | None = None,
    *,
    ax: "Axes | None" = None,
    max_points: int | None = 3000,
    size: float = 1.0,
    source_color: "ColorType" = "tab:orange",
    target_color: "ColorType" = "tab:blue",
    title: str | None = None,
) -> "Axes":
    """The target cloud and the source cloud mapped into the target frame by `transform`
    (`T_target_source`, an `SE3`; `None` draws the source as given), in one 3D scatter.

    **Returns:** the axes.
    """
    source = np.asarray(source if transform is None else transform @ np.asarray(source))
    ax = plot_points(
        target,
        ax=ax,
        max_points=max_points,
        size=size,
        color=target_color,
        label="target",
        equal=False,
    )
    plot_points(
        source,
        ax=ax,
        max_points=max_points,
        size=size,
        color=source_color,
        label="source",
        equal=True,
    )
    if title is not None:
        ax.set_title(title)
    return ax


# ---- pose graphs ------------------------------------------------------------------------------


def plot_pose_graph(
    graph: "PoseGraph | AbstractGroup",
    poses: AbstractGroup | None = None,
    *,
    edges: ArrayLike | None = None,
    ax: "Axes | None" = None,
    odometry: bool = True,
    loop_closures: bool = True,
    frames: float = 0.0,
    color: "ColorType" = "tab:blue",
    odometry_color: "ColorType" = "0.55",
    loop_color: "ColorType" = "tab:red",
    linewidth: float = 0.6,
    label: str | None = None,
    equal: bool = True,
) -> "Axes":
    """Draw a 2D or 3D pose graph: the poses' positions joined in index order (odometry edges,
    `|i - j| = 1`) and the other edges (loop closures) as segments.

    **Arguments:**

    - `graph`: a `lieax.graph.PoseGraph`, or a batch of `SE2` / `SE3` poses with `edges`.
    - `poses`: poses to draw in place of `graph.poses` (e.g. `optimize(graph).poses`).
    - `edges`: `(m, 2)` pose indices, when `graph` is a batch of poses (default: none).
    - `odometry`, `loop_closures`: draw the consecutive / the other edges.
    - `frames`: draw every pose's axes with this length (0: none).
    - `label`: legend label of the positions.

    **Returns:** the axes.
    """
    if hasattr(graph, "poses") and hasattr(graph, "edges"):
        poses = graph.poses if poses is None else poses
        edges = graph.edges if edges is None else edges
    else:
        poses = graph if poses is None else poses
    edges = np.zeros((0, 2), int) if edges is None else np.asarray(edges).reshape(-1, 2)
    _, position = _rotations_and_positions(poses, None)
    d = position.shape[1]
    ax = _axes(ax, d)
    i, j = edges[:, 0], edges[:, 1]
    consecutive = np.abs(i - j) == 1
    if loop_closures and np.any(~consecutive):
        lines = _segments(position[i[~consecutive]], position[j[~consecutive]])
        ax.plot(*lines.T, color=loop_color, linewidth=0.5 * linewidth, alpha=0.6)
    if odometry and np.any(consecutive):
        lines = _segments(position[i[consecutive]], position[j[consecutive]])
        ax.plot(*lines.T, color=odometry_color, linewidth=linewidth)
    ax.plot(*position.T, ".", color=color, markersize=2.0, label=label)
    if frames > 0:
        plot_frames(poses, ax=ax, length=frames, linewidth=0.5 * linewidth, equal=False)
    if equal:
        set_axes_equal(ax)
    return ax


# ---- cost curves ------------------------------------------------------------------------------


def plot_cost(
    history: ArrayLike | _CostHistory,
    *,
    ax: "Axes | None" = None,
    label: str | None = None,
    log: bool = True,
    marker: str | None = "o",
    color: "ColorType | None" = None,
    alpha: float = 1.0,
) -> "Axes":
    """Cost per iteration: `history` is a cost history array `(iterations + 1,)` (NaN padding
    after the last iteration is dropped), a batch of them `(b, iterations + 1)` (one line each,
    as a vmapped solve returns them), or anything with a `cost_history` attribute
    (`lieax.lstsq.Solution`, `lieax.graph.OptimizeResult`). Iteration 0 is the initial cost.

    **Returns:** the axes.
    """
    history = np.asarray(getattr(history, "cost_history", history), dtype=float)
    if history.ndim == 1:
        history = history[None]
    history = history.reshape(-1, history.shape[-1])
    ax = _axes(ax, 2)
    for k, row in enumerate(history):
        finite = np.isfinite(row)
        last = int(np.max(np.nonzero(finite)[0])) + 1 if finite.any() else 0
        ax.plot(
            np.arange(last),
            row[:last],
            marker=marker,
            markersize=3,
            color=color,
            alpha=alpha,
            label=label if k == 0 else None,
        )
    if log:
        ax.set_yscale("log")
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("iteration")
    ax.set_ylabel("cost")
    return ax
