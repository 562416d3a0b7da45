r"""The two parts the ICP loop (`lieax.icp._loop`) is handed: a `Step`, which updates the pose from
matched pairs, and a `Matcher`, which finds the pairs. The public entry points choose them once
(`point_to_point`, `point_to_plane`, `gicp`; `lieax.icp._matchers.matcher_for` for `search=`)
and pass them to the loop as static arguments: module-level constants of module-level functions,
so that equal choices hash equal and share one compiled loop. The loop knows neither kind by
name (small_gicp's `Registration` template, handed its factor, search and optimizer: Koide,
small_gicp, `registration/registration.hpp`).

Each part is a tuple of pure functions, as optax's `(init, update)` pairs.
"""

from collections.abc import Callable
from typing import NamedTuple


class Step(NamedTuple):
    r"""A pose update from matched pairs.

    - `name`: which cost it minimizes, for the implicit derivatives of `lieax.icp._implicit`
      (`"point"`, `"plane"` or `"gicp"`); the loop does not read it.
    - `update(params, source, source_rows, matched, matched_rows, inliers, loss_weights)`: the
      SE3 parameters after one update from `params` (about the centroids): `source` `(n, 3)`,
      `matched` `(n, 3)` the matched target points, `source_rows` and `matched_rows` the step's
      per-point data of the source and of the matched target points (pytrees of arrays with
      `n` rows, or None; rows that are not inliers hold zeros), `inliers` `(n,)` bools,
      `loss_weights` the IRLS weights $\rho'(s)$ as a function of squared residuals.
    """

    name: str
    update: Callable


class Matcher(NamedTuple):
    """A correspondence search inside the loop.

    - `build(target, mask, max_distance)`: the index of the target (as given, not centred); it
      has `points` `(N, 3)`, `order` `(N,)` (the target row of each slot) and `valid` `(N,)`.
    - `start(n, dtype)`: the search's own state before the first match (a pytree, or None).
    - `match(index, queries, max_distance, mask, carry)`: `(slot, found, carry)`, the slots of
      the nearest valid target points within `max_distance` of the queries (`found` False
      where there is none), and the search's state for the next call. `mask` marks the queries
      to match (False: padding, or a problem that stopped).
    """

    build: Callable
    start: Callable
    match: Callable
