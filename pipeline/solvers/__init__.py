"""Generic numerical solvers that the method's problems share (no knowledge of cameras or surfaces).

- :mod:`~pipeline.solvers.pcg` and :mod:`~pipeline.solvers.multigrid`: grid systems (below);
- :mod:`~pipeline.solvers.robust_lm`: robust nonlinear least squares of a few parameters
  (Levenberg-Marquardt, soft-L1 loss), for the geometric fits and the mesh registration;
- :mod:`~pipeline.solvers.order`: ``np.percentile`` of large samples to the bit, faster;
- :mod:`~pipeline.solvers.components`: connected components and their areas, a mask's bounding box.

A *grid system* is a symmetric linear system on an (H, W) grid: a masked graph Laplacian over
4-neighbour edges plus a diagonal term. It lives on arrays padded with one cell of zeros on every
side (interior cells 1..H, 1..W), so that the stencils need no bounds checks:

- ``ex[i, j]``: weight of the edge (i, j) - (i, j + 1) (0 on edges that leave the system);
- ``ey[i, j]``: weight of the edge (i, j) - (i + 1, j);
- ``wd[i, j]``: the diagonal (data) term;
- ``dg[i, j]``: the diagonal of A = wd + the weights of the 4 edges; ``idg = 1 / dg``, or 0 for a
  cell that is not in the system (its value stays 0).

``A x = dg * x - sum over the 4 edges of weight * x_neighbour``; red cells have (i + j) even. The
weights are float32, the right-hand side and the solution float64. :func:`solve_grid_system`
solves it by conjugate gradients (:mod:`~pipeline.solvers.pcg`) preconditioned with one geometric
multigrid V-cycle (:mod:`~pipeline.solvers.multigrid`): the exact least-squares solution on the
masked domain, not a periodic (Fourier) approximation. The normal integration
(:mod:`pipeline.surface.integration`) assembles such systems.

The parallel kernels must not run concurrently from two threads (numba's workqueue layer aborts):
:mod:`pipeline.stages` calls them from its main thread only. In numba, ``float(x)`` of a float32
stays float32; ``np.float64(x)`` is used where it matters.
"""

from .components import bounding_box, labelled
from .multigrid import Multigrid
from .order import percentile
from .pcg import pcg, solve_grid_system
from .robust_lm import robust_gauss_newton, robust_scale

__all__ = [
    "Multigrid",
    "bounding_box",
    "labelled",
    "pcg",
    "percentile",
    "robust_gauss_newton",
    "robust_scale",
    "solve_grid_system",
]
