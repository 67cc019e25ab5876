"""A take read from an animation, the material fitted to it, and its motion continued.

SPEC.md section 5, "Recovering material" [L14]: the frames of an input animation (the *take*)
become modal coordinates through their RS coordinates (``poses.poses_to_modal``); a space-time
solve with those frames as keyframe constraints optimises the modal material (per-mode
eigenvalue lambda_k = omega_k^2 [rad^2/s^2], damping d_k [1/s] and the sampling S of the
candidate modes, ``spacetime.solve(optimise_material=True)``); the fitted material then runs
freely from the fit's last two frames (position and velocity there) to continue the motion.

Everything is in the body's object space (metres), frames are scene frames, h [s] per frame.
"""
import dataclasses

import numpy as np
import scipy.optimize

from . import materials, poses, spacetime

# Weight of a take frame against one frame's dynamics (``spacetime.suggest_weights``
# tightness). The take is data with noise the modes cannot express, not a target to meet
# exactly: at 1 the fitted motion follows the frames closely while E_f still tells the material.
FIT_TIGHTNESS = 1.0
# rho of the pull toward the prepared material (``spacetime`` "Material regulariser"). A take's
# frames determine the material, so nothing need hold it: with the automatic rho a bar whose
# first frequency is 0.537 Hz (prepared uniform 0.497) fitted 0.500, with none 0.537.
FIT_MATERIAL_WEIGHT = 0.0


def take_to_modal(body, rest, take_poses, step=None):
    """The take's frames as deformer inputs, and how much of them the modes cannot express.

    body: ``PreparedBody``; rest (n, 3) [m] base vertices at rest; take_poses (k, n, 3) [m];
    step(i) is called after frame i is read (progress; it may raise to stop).
    Returns (inputs (k, m) modal coordinates, branch-continuous from frame to frame;
    residuals (k,) [m] per frame the RMS over vertices of |reconstruction - pose|).
    """
    take_poses = np.asarray(take_poses, dtype=np.float64)
    inputs = poses.poses_to_modal(body, take_poses, step)
    return inputs, position_rms(body.surface_positions(rest, inputs), take_poses)


def position_rms(a, b):
    """(k,) per frame the RMS over vertices of the distance between a and b (k, n, 3) [m]."""
    return np.sqrt(np.mean(np.sum((np.asarray(a) - np.asarray(b)) ** 2, axis=2), axis=1))


@dataclasses.dataclass
class FittedMaterial:
    """A modal material fitted to a take's frames first_frame..last_frame (scene frames).

    eigenvalues, damping (r,) [rad^2/s^2], [1/s]; sampling S (m, r) of the body's m candidate
    modes; prepared_eigenvalues, prepared_damping (r,) what the fit started from; state (2, r)
    the fitted z at the last two frames of the range (they carry position and velocity);
    h [s] per frame; scheme: the time discretisation of E_f (continue with the same);
    residual [m]: RMS over the take frames in the range of |fitted surface - take pose|;
    worst_frame: the scene frame where that distance is largest; converged, reason: the solve's.
    """
    eigenvalues: np.ndarray
    damping: np.ndarray
    sampling: np.ndarray
    prepared_eigenvalues: np.ndarray
    prepared_damping: np.ndarray
    state: np.ndarray
    first_frame: int
    last_frame: int
    h: float
    scheme: str
    residual: float
    worst_frame: int
    converged: bool = True
    reason: str = ""

    ARRAYS = ("eigenvalues", "damping", "sampling", "prepared_eigenvalues", "prepared_damping",
              "state")

    def to_dict(self):
        """Plain Python (lists, numbers, str): what an ID property can hold."""
        out = dataclasses.asdict(self)
        for name in self.ARRAYS:
            out[name] = np.asarray(out[name], dtype=np.float64).ravel().tolist()
        out["shape"] = list(np.shape(self.sampling))
        return out

    @classmethod
    def from_dict(cls, data):
        """The inverse of ``to_dict``."""
        m, r = (int(v) for v in data["shape"])
        values = {f.name: data[f.name] for f in dataclasses.fields(cls)}
        for name in cls.ARRAYS:
            values[name] = np.asarray(values[name], dtype=np.float64)
        values["sampling"] = values["sampling"].reshape(m, r)
        values["state"] = values["state"].reshape(2, r)
        return cls(**values)

    @property
    def frequencies(self):
        """(r,) fitted frequencies [Hz]."""
        return np.sqrt(self.eigenvalues) / (2.0 * np.pi)

    @property
    def prepared_frequencies(self):
        """(r,) the prepared material's frequencies [Hz]."""
        return np.sqrt(self.prepared_eigenvalues) / (2.0 * np.pi)


def fitted_modes(candidates):
    """How many modes a fit optimises out of ``candidates``: half, so the sampling S has as
    many candidates again to choose from. Measured on the seed's bar (12 candidates): 6 converged
    in 7 material rounds (continuation error 0.0025 m), 8 (``problems.optimised_modes``) had
    not converged in 20, 12 (a square S, not optimised) converged with 0.0039 m."""
    return max(1, candidates // 2)


def fit_problem(body, frames, inputs, h, damping_mass=0.0, damping_stiffness=0.0,
                optimised=True, material_freedom=spacetime.MATERIAL_FREEDOM):
    """The space-time problem of a fit: frames (k,) consecutive scene frames of the take in
    the fit range, inputs (k, m) their modal coordinates, as keyframes; free start (the take
    does not start at rest). With ``optimised`` the material optimises ``fitted_modes(m)``
    modes, else all m."""
    frames = np.asarray(frames, dtype=np.int64)
    m = body.deformer.num_coords
    r = fitted_modes(m) if optimised else m
    eigenvalues = body.linear_modes.eigenvalues[:r]
    damping = spacetime.rayleigh_damping(eigenvalues, damping_mass, damping_stiffness)
    _, weight = spacetime.suggest_weights(h, eigenvalues, damping, tightness=FIT_TIGHTNESS)
    keyframes = spacetime.Keyframes(frames - frames[0], inputs, weight)
    return spacetime.SpaceTimeProblem(int(frames[-1] - frames[0] + 1), h, eigenvalues, damping,
                                      body.deformer, keyframes=keyframes, fix_start=False,
                                      material_freedom=material_freedom,
                                      material_weight=FIT_MATERIAL_WEIGHT)


def fit_material(body, rest, frames, take_poses, inputs, h, damping_mass=0.0,
                 damping_stiffness=0.0, optimise=True, material_freedom=spacetime.MATERIAL_FREEDOM,
                 iterations=20, callback=None, should_cancel=None):
    """Fit the modal material to the take's frames (k,) [scene frames, consecutive], their
    poses (k, n, 3) [m] and modal coordinates inputs (k, m) (``take_to_modal``).

    optimise False keeps the prepared material (the uniform baseline of the seed's experiment).
    iterations: material rounds; callback, should_cancel: as ``spacetime.solve``.
    Returns a ``FittedMaterial``.
    """
    frames = np.asarray(frames, dtype=np.int64)
    if len(frames) < 3 or np.any(np.diff(frames) != 1):
        raise ValueError("a fit needs at least 3 consecutive take frames")
    problem = fit_problem(body, frames, inputs, h, damping_mass, damping_stiffness, optimise,
                          material_freedom)
    result = spacetime.solve(problem, optimise_material=optimise,
                             iterations=iterations if optimise else None,
                             callback=callback, should_cancel=should_cancel)
    errors = position_rms(body.surface_positions(rest, result.inputs), take_poses)
    return FittedMaterial(
        result.eigenvalues.copy(), result.damping.copy(), result.sampling.copy(),
        problem.eigenvalues.copy(), problem.damping.copy(), result.Z[-2:].copy(),
        int(frames[0]), int(frames[-1]), float(h), result.scheme,
        float(np.sqrt(np.mean(errors ** 2))), int(frames[np.argmax(errors)]),
        bool(result.converged), result.reason)


def continue_motion(fitted, count):
    """Deformer inputs (count, m) of the ``count`` frames after the fit's last frame: the
    fitted material's free motion z'' + D z' + Lambda z = 0 from the fit's last two frames,
    with the fit's own time discretisation (so it goes on as the fitted motion would)."""
    Z = spacetime.simulate_modal(fitted.eigenvalues, fitted.damping, fitted.state[0],
                                 fitted.state[1], int(count) + 2, fitted.h, fitted.scheme)
    return Z[2:] @ fitted.sampling.T


# --- the fitted material in a simulation ------------------------------------------------------

def fitted_stiffness(fitted, prepared_stiffness):
    """(m, m) the reduced stiffness K [J per unit s^2] whose restriction to the fitted modes
    s = S z is A = G^1/2 Lambda G^1/2 (G = S^T S; for unit, orthogonal columns of S simply the
    fitted Lambda), and the prepared stiffness K0 (m, m) (a potential's ``rest_hessian``) on
    what is K0-orthogonal to them. Split s = S z + c with z = P s, P = (S^T K0 S)^-1 S^T K0:
    s^T K s = z^T A z + c^T K0 c, so K = K0 - K0 S P + P^T A P, positive definite with A and K0.
    (Keeping K0 on a plainly orthogonal complement instead was not: a fitted mode mixing in a
    stiff candidate mode made K indefinite.)"""
    S = fitted.sampling
    K0 = np.asarray(prepared_stiffness, dtype=np.float64)
    values, vectors = np.linalg.eigh(S.T @ S)
    root = (vectors * np.sqrt(values)) @ vectors.T
    A = root @ np.diag(fitted.eigenvalues) @ root
    K0S = K0 @ S
    P = np.linalg.solve(S.T @ K0S, K0S.T)
    K = K0 - K0S @ P + P.T @ A @ P
    return 0.5 * (K + K.T)


def fitted_rayleigh(fitted):
    """(alpha [1/s], beta [s]) >= 0 of the Rayleigh damping alpha + beta lambda_k nearest the
    fitted per-mode damping d_k, relative to each d_k's scale (``scipy.optimize.nnls``): what
    a simulation, whose damping is Rayleigh, can take of the fit."""
    scale = 2.0 * np.sqrt(fitted.eigenvalues)            # d_k's scale: twice omega_k
    A = np.stack([np.ones_like(scale), fitted.eigenvalues], axis=1) / scale[:, None]
    (alpha, beta), _ = scipy.optimize.nnls(A, fitted.damping / scale)
    return float(alpha), float(beta)


class FittedPotential(materials.PotentialAccessors):
    """A reduced potential (anything with ``evaluate``, ``rest_hessian``, ``num_coords``) with
    its stiffness at rest replaced by ``fitted_stiffness``: V(s) + 1/2 s^T (K - K0) s. For the
    Linear material that is exactly 1/2 s^T K s; a nonlinear one keeps its own nonlinearity.
    Other attributes (the material the barriers read) are the wrapped potential's."""

    def __init__(self, potential, fitted):
        self.potential = potential
        self.num_coords = potential.num_coords
        self.rest_hessian = fitted_stiffness(fitted, potential.rest_hessian)
        self.correction = self.rest_hessian - potential.rest_hessian

    def __getattr__(self, name):            # only called for attributes not found above
        if name in ("potential", "correction"):
            raise AttributeError(name)
        return getattr(self.potential, name)

    def evaluate(self, s, order=2):
        energy, grad, hess = self.potential.evaluate(s, order)
        Cs = self.correction @ np.asarray(s, dtype=np.float64)
        energy = energy + 0.5 * float(np.asarray(s) @ Cs)
        return (energy, None if grad is None else grad + Cs,
                None if hess is None else hess + self.correction)


def continuation_state(fitted):
    """(s (m,), ds/dt (m,)) at the fit's last frame for a simulation started there: the
    position, and the velocity of the fitted motion (backward difference plus half a step of
    its acceleration, second order in h)."""
    z_prev, z = fitted.state
    velocity = (z - z_prev) / fitted.h
    acceleration = -fitted.eigenvalues * z - fitted.damping * velocity
    return fitted.sampling @ z, fitted.sampling @ (velocity + 0.5 * fitted.h * acceleration)
