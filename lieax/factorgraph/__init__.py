"""Sparse nonlinear least squares over factor graphs: variable kinds, factor kinds written for
one instance, block-sparse normal equations, Levenberg-Marquardt, Schur elimination, marginals.

```python
poses = Var(SE2(params), fixed=[0], name="poses")
between = Factor(between_residual, (poses[i], poses[j]), measured, sqrt_information=R)
graph = FactorGraph([between, gps])
result = graph.solve()
```

A variable kind (`Var`) is a lieax group, an array or a pytree of them, with many instances
stored batched; a factor kind (`Factor`) is one residual function vmapped over its instances,
with index arrays per argument (Dellaert and Kaess, "Factor graphs for robot perception",
2017). `FactorGraph` analyses the structure once on the host; `solve` runs the whole
Levenberg-Marquardt loop in one jitted `lax.while_loop` with the dense, sparse Cholesky
(host multifrontal) or PCG solver, optionally eliminating a kind by the Schur complement
(Triggs et al., "Bundle adjustment — a modern synthesis", 2000). Conventions: docs/conventions.md
(right perturbation, translation-first tangents).
"""

from ..lstsq._solution import SolveResult
from ._factors import Factor, square_root_information
from ._graph import FactorGraph
from ._marginals import marginal_covariances
from ._structure import connected_components
from ._variables import Var, VarRef

__all__ = [
    "Factor",
    "FactorGraph",
    "SolveResult",
    "Var",
    "VarRef",
    "connected_components",
    "marginal_covariances",
    "square_root_information",
]
