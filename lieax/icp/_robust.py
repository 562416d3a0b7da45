r"""Robust losses inside the ICP loops: IRLS weights $\rho'(s)$ of squared residuals $s$.

The `lieax.lstsq` losses (and no loss) travel as a `(kind, scale)` pair: the ICP loops take the
kind as a static argument (one compiled loop per kind of loss, with that loss's weights only: a
`lax.switch` over all five would compile every branch into every loop) and the scale traced (a
new scale does not recompile); any other object with a `weight(s)` method is a static argument.
"""

import functools
from typing import Protocol

import jax
import jax.numpy as jnp

from ..lstsq import Cauchy, GemanMcClure, Huber, Tukey

KNOWN_LOSSES = (None, Huber, Cauchy, Tukey, GemanMcClure)


class WeightedLoss(Protocol):
    r"""The type of ICP's `loss=`: anything with a `weight(s)` method giving the IRLS weights
    $\rho'(s)$ of squared residuals `s` (the `lieax.lstsq` losses, or a hashable object of the
    user's)."""

    def weight(self, s: jax.Array, /) -> jax.Array: ...


def split_loss(loss):
    """`(dynamic, static)`: no loss and the `lieax.lstsq` losses become a `(kind, scale)` pair, the
    kind a Python int, the scale traced, so that every scale shares one compiled loop
    (`lieax.icp._registration` checks a concrete scale; a traced one that is not positive and
    finite ends the loop `INVALID`); any other object with a `weight(s)` method is passed as a
    static argument (it must be hashable)."""
    if loss is None:
        return (0, 1.0), None
    if type(loss) in KNOWN_LOSSES:
        return (KNOWN_LOSSES.index(type(loss)), loss.scale), None
    if not callable(getattr(loss, "weight", None)):
        raise TypeError(
            f"loss must have a weight(s) method (see lieax.lstsq losses), got {loss!r}."
        )
    return None, loss


def loss_weights(loss, static_loss, squared):
    r"""IRLS weights $\rho'(s)$ of squared residuals (differentiable in `s` and the scale); a
    concrete kind computes that loss's weights alone, a traced one switches over all of them."""
    if static_loss is not None:
        return static_loss.weight(squared)
    kind, scale = loss
    scale = jnp.asarray(scale).astype(squared.dtype)
    branches = [lambda s, c: jnp.ones_like(s)] + [
        functools.partial(_loss_weight, cls) for cls in KNOWN_LOSSES[1:]
    ]
    if isinstance(kind, int):
        return branches[kind](squared, scale)
    return jax.lax.switch(kind, branches, squared, scale)


def _loss_weight(cls, squared, scale):
    return cls(scale).weight(squared)
