"""After a solve: how far the reduced model is from full RS, and how much the body stretches.

Two questions the tool must answer when a big edit looks wrong (issue 12): was the reduced RS
model off its training range (``reduced_error``: reduced positions against the full RS
reconstruction ``rs.PoissonReconstruction`` of the same RS coordinates), or did the targets ask
the body to stretch (``region_stretch``: the largest principal stretch the RS coordinates carry
near a handle)? Both are measured on a few frames (``telling_frames``) since a full RS
reconstruction costs one Poisson solve per frame.

Shapes and units: modal_rs (E, 9, m) linear RS coordinates per unit deformer input (rows
omega (3) [rad], then strain eps (6: xx, xy, xz, yy, yz, zz)); Z (F, m) deformer inputs per frame;
X (N, 3) tet nodes [m]; T (E, 4).
"""

import numpy as np

from . import cubature, rs

REDUCED_ERROR_TOLERANCE = 0.01   # fraction of the bounding-box diagonal worth a warning


def telling_frames(modal_rs, Z, count=4):
    """Indices (<= count,) ascending of the frames of Z (F, m) with the largest rotation.

    Reduced RS errors grow with rotation (off the training range first), so these frames bound
    the error of the rest; the largest-strain frame is added when it is not among them.
    """
    Z = np.atleast_2d(np.asarray(Z, dtype=np.float64))
    rotation, strain = cubature.pose_extremes(modal_rs, Z)
    picks = list(np.argsort(rotation)[::-1][:max(int(count) - 1, 1)])
    picks.append(int(np.argmax(strain)))
    return np.unique(np.asarray(picks, dtype=np.int64))[:max(int(count), 1)]


def reduced_error(deformer, recon, modal_rs, Z, X):
    """(F,) largest vertex |u_reduced - u_full| per frame, as a fraction of the diagonal.

    deformer: a ``reduced.ReducedRS`` (with its basis) or anything with ``displacement(z)``
    (N, 3) [m]; recon: the body's ``rs.PoissonReconstruction`` (same pins as the deformer);
    u_full = recon.reconstruct(modal_rs z), one Poisson solve per frame (few frames only).
    """
    Z = np.atleast_2d(np.asarray(Z, dtype=np.float64))
    diagonal = float(np.linalg.norm(np.ptp(np.asarray(X), axis=0)))
    out = np.empty(len(Z))
    for k, z in enumerate(Z):                       # one Poisson solve per frame
        full = recon.reconstruct(np.asarray(modal_rs) @ z)
        reduced = np.reshape(deformer.displacement(z), (-1, 3))
        out[k] = np.linalg.norm(reduced - full, axis=1).max() / diagonal
    return out


def principal_stretches(rs_coordinates):
    """(E, 3) ascending eigenvalues of the strain eps of RS coordinates (E, 9).

    In RS coordinates the deformation is F = exp([omega]x)(I + eps), so the principal stretches
    are 1 + these eigenvalues (eps > 0 stretches, < 0 compresses) [dimensionless].
    """
    y = np.asarray(rs_coordinates, dtype=np.float64)
    eps = np.einsum("ek,kab->eab", y[:, 3:], rs.STRAIN_BASIS)
    return np.linalg.eigvalsh(0.5 * (eps + eps.transpose(0, 2, 1)))


def region_stretch(modal_rs, Z, tets):
    """Largest principal stretch - 1 (fraction, 0.2 = 20 %) over frames Z (F, m) and tets (k,).

    Z: the frames to check (e.g. ``telling_frames``); tets: the handle's region
    (``region_tets``). Negative when the region only compresses.
    """
    Z = np.atleast_2d(np.asarray(Z, dtype=np.float64))
    tets = np.asarray(tets, dtype=np.int64)
    y = np.einsum("ekm,fm->fek", np.asarray(modal_rs)[tets], Z).reshape(-1, 9)
    return float(principal_stretches(y)[:, -1].max())


def region_tets(T, nodes):
    """Indices of the tets of T (E, 4) touching any node in ``nodes`` (k,) (a handle's region)."""
    mask = np.zeros(int(np.max(T)) + 1, dtype=bool)
    mask[np.asarray(nodes, dtype=np.int64)] = True
    return np.flatnonzero(mask[np.asarray(T)].any(axis=1))
