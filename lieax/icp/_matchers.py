"""The correspondence searches of the ICP loop, as `lieax.icp._parts.Matcher`s, one per backend of
`lieax.icp._search`: `matcher_for(name)` is chosen once by the entry points.

- `"kdtree"`: the k-d tree (native, or on the host), warm-started from the last match
  (`_host_kdtree.track_in_kdtree`): exact every iteration, the host sees only the queries whose
  match may have changed.
- `"grid"`, `"brute"`: exact in every iteration (`_search.match`).
"""

import jax.numpy as jnp

from . import _grid, _host_kdtree, _search
from ._parts import Matcher


def _build_kdtree(target, mask, max_distance):
    return _host_kdtree.build_kdtree(target, mask)


def _build_grid(target, mask, max_distance):
    return _grid.build_grid(target, mask, cell_size=max_distance)


def _build_brute(target, mask, max_distance):
    return _search.build_index(target, mask, search="brute")


def _no_state(n, dtype):
    return None


def _track(index, queries, max_distance, mask, warm):
    """Matches within the radius, or twice it when the tree is asked for two neighbours (the
    loop tests the distances against the radius). The tree's distances go unused: XLA drops
    their gather, a pass over the rows per iteration."""
    slot, _, warm = _host_kdtree.track_in_kdtree(index, queries, max_distance, warm, mask=mask)
    return slot, warm.slot >= 0, warm


def _exact(index, queries, max_distance, mask, carry):
    slot, d2 = _search.match(index, queries, max_distance, mask)
    return slot, jnp.isfinite(d2), carry


KDTREE = Matcher(_build_kdtree, _host_kdtree.cold_start, _track)
GRID = Matcher(_build_grid, _no_state, _exact)
BRUTE = Matcher(_build_brute, _no_state, _exact)
_MATCHERS = {"kdtree": KDTREE, "grid": GRID, "brute": BRUTE}


def matcher_for(name) -> Matcher:
    """The `Matcher` of a backend name (`"auto"` resolved: `lieax.icp._search.check_icp_search`)."""
    return _MATCHERS[name]
