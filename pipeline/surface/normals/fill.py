"""Hole filling of a normal field: a harmonic (discrete Laplace) interpolation from the neighbours."""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sp
import scipy.sparse.linalg as spla


def harmonic_fill(
    normals: np.ndarray, albedo: np.ndarray, known: np.ndarray, holes: np.ndarray
) -> np.ndarray:
    """Fill ``holes`` of the normals and the albedo in place by the discrete Laplace equation.

    Each hole pixel becomes the mean of its 4-neighbours that are known or holes; known
    pixels are Dirichlet data. The filled normals are renormalised (the harmonic mean of
    unit vectors with n_z < 0 has n_z < 0: maximum principle). Hole components with no
    known 4-neighbour are not filled.

    Parameters
    ----------
    normals : (H, W, 3) float32
        Unit normals where ``known``; the holes' values are written.
    albedo : (H, W) float32
        Likewise.
    known : (H, W) bool
        Pixels whose normal and albedo are data.
    holes : (H, W) bool
        Pixels to fill.

    Returns
    -------
    (H, W) bool
        The pixels filled (holes in a component with no known 4-neighbour are not).
    """
    filled = np.zeros_like(holes)
    if not holes.any():
        return filled
    # Work in the holes' bounding box grown by one pixel (the known neighbours).
    rows, cols = np.nonzero(holes)
    r0, r1 = max(rows.min() - 1, 0), min(rows.max() + 2, holes.shape[0])
    c0, c1 = max(cols.min() - 1, 0), min(cols.max() + 2, holes.shape[1])
    box = (slice(r0, r1), slice(c0, c1))
    hole_b, known_b = holes[box], known[box]
    labels, _ = ndi.label(hole_b)  # 4-connectivity
    touching = ndi.binary_dilation(known_b) & hole_b
    fill = hole_b & np.isin(labels, np.unique(labels[touching]))
    if not fill.any():
        return filled
    h, w = hole_b.shape
    values = (
        np.concatenate([normals[box], albedo[box][..., None]], axis=-1)
        .reshape(h * w, 4)
        .astype(np.float64)
    )
    fill_flat = np.flatnonzero(fill)
    index = np.full(h * w, -1, dtype=np.int64)
    index[fill_flat] = np.arange(fill_flat.size)
    rr, cc = np.divmod(fill_flat, w)
    known_flat = known_b.ravel()
    diag = np.zeros(fill_flat.size)
    rhs = np.zeros((fill_flat.size, 4))
    ii, jj = [], []
    for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        r, c = rr + dr, cc + dc
        inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
        nb = np.where(inside, r * w + c, 0)
        nb_known = inside & known_flat[nb]
        nb_fill = inside & (index[nb] >= 0)
        diag += nb_known | nb_fill
        rhs[nb_known] += values[nb[nb_known]]
        ii.append(np.flatnonzero(nb_fill))
        jj.append(index[nb[nb_fill]])
    ii_all, jj_all = np.concatenate(ii), np.concatenate(jj)
    diag_idx = np.arange(fill_flat.size)
    A = sp.csc_matrix(
        (
            np.concatenate([diag, -np.ones(ii_all.size)]),
            (np.concatenate([diag_idx, ii_all]), np.concatenate([diag_idx, jj_all])),
        ),
        shape=(fill_flat.size, fill_flat.size),
    )
    sol = np.asarray(spla.spsolve(A, rhs)).reshape(fill_flat.size, 4)
    n = sol[:, :3] / np.linalg.norm(sol[:, :3], axis=1, keepdims=True)
    at = (rr + r0, cc + c0)
    normals[at] = n
    albedo[at] = sol[:, 3]
    filled[at] = True
    return filled
