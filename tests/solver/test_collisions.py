"""Collision oracles: reduced RS bodies (``dynamics.Simulation``) against ``contact`` colliders.

Oracles: the time a dropped body first touches (free fall, sqrt(2 h / g)), the barrier's band
(no sample below the surface by more than the thickness), coming to rest (speed and kinetic
energy against m g h), a frictionless slide at exactly g sin(theta), Coulomb sticking for
mu > tan(theta), and a swinging bar stopped by a wall it would otherwise pass.

Bodies are built like ``test_dynamics.build_body`` (modes, second-order RS basis, cubature),
here with an optional rigid placement of the rest mesh; the file runs in about 5 s.
"""

import time

import igl
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from solver import (contact, dynamics, fem, frames, integrators, materials, meshgen, modes,
                    reduced, rs)

G = 9.81
GRAVITY = np.array([0.0, 0.0, -G])
FPS = 24
SUB = 4


def build_body(size, cells, youngs, poisson=0.3, density=1000.0, num_modes=8, pinned=False,
               rotation=np.eye(3), offset=np.zeros(3), samples=60):
    """Box body (pinned at its x = 0 face, or free) with its rest mesh X = R X_box + offset,
    its ReducedRS, exact linear potential and contact samples (surface_samples of the boundary
    triangles: indices, rows (3k, rB), weights, masses)."""
    X, T = meshgen.box_tet_mesh(size, cells)
    pins = np.flatnonzero(X[:, 0] < 1e-9) if pinned else None
    X = X @ np.asarray(rotation).T + offset
    masses = fem.lumped_masses(X, T, density)
    result = modes.linear_modes(fem.stiffness_matrix(X, T, youngs, poisson), masses, num_modes,
                                pins)
    modal_rs = rs.linear_rs(rs.rs_operator(X, T), result.vectors)
    recon = rs.PoissonReconstruction(X, T, pins)
    deformer, _ = reduced.prepare_reduced_rs(
        X, T, masses, result.vectors, result.eigenvalues, recon, modal_rs=modal_rs,
        max_size=30, num_snapshots=40, max_tets=60, num_poses=30)
    mu, lam = fem.lame_parameters(youngs, poisson)
    potential = materials.ReducedPotential.exact(materials.Linear(mu, lam), modal_rs,
                                                 fem.tet_volumes(X, T))
    faces = igl.boundary_facets(T)
    faces = faces[0] if isinstance(faces, tuple) else faces
    idx, weights = contact.surface_samples(X, faces, samples)
    B = deformer.basis
    rows = B.reshape(len(X), 3, -1)[idx].reshape(-1, B.shape[1])
    # Each sample carries the mass of the surface area it represents (its share of the body).
    sample_masses = masses.sum() * weights / weights.sum()
    return dict(X=X, T=T, masses=masses, deformer=deformer, potential=potential, pins=pins,
                idx=idx, rows=rows, weights=weights, sample_masses=sample_masses,
                omega=np.sqrt(result.eigenvalues))


def body_contact(body, colliders):
    return contact.Contact(colliders, body["X"][body["idx"]], body["rows"], body["weights"],
                           body["sample_masses"])


def simulate(body, colliders, frames, **kwargs):
    """Run ``frames`` frames at 24 fps: (trajectory, the Simulation, wall seconds)."""
    con = body_contact(body, colliders) if colliders else None
    sim = dynamics.Simulation(body["deformer"], body["X"], body["masses"], body["potential"],
                              1.0 / FPS, contact=con, **kwargs)
    start = time.perf_counter()
    trajectory = sim.run(frames)
    return trajectory, sim, time.perf_counter() - start


def quad(corners, thickness=0.02, friction=0.0, damping=0.5):
    """Two-triangle collider facing along (c1 - c0) x (c2 - c0)."""
    return contact.MeshCollider(np.asarray(corners, dtype=np.float64), [[0, 1, 2], [0, 2, 3]],
                                thickness=thickness, friction=friction, damping=damping)


def centre_of_mass(body, trajectory):
    x = trajectory.world_positions(body["X"], body["deformer"].basis)
    return np.einsum("k,fki->fi", body["masses"], x) / body["masses"].sum()


# 1. A soft cube dropped on a floor -------------------------------------------------------------

def test_dropped_cube_touches_on_time_stays_outside_and_comes_to_rest():
    """0.2 m cube, 4^3 cells, E = 2e4 Pa, nu = 0.3, 1000 kg/m^3 (8 kg; its weight alone squeezes
    it by about 5 %), lowest point 1 m above a static floor quad (thickness 2 cm, collider
    damping 0.5, no friction); material damping: stiffness damping giving 5 % at the first
    mode. 24 fps, 4 substeps, 3 s. (At one step per frame it is nearly at rest by 3 s but not
    within these thresholds: kinetic energy 1.6e-4 m g h, 0.16 cm/s.)

    - First touch: the centre of mass falls exactly as 1/2 g t^2 (Newmark) until contact acts,
      so the first frame whose centre leaves that parabola is the frame the contact started in;
      its end is within one frame (1/24 s) of sqrt(2 h / g).
    - No contact sample is ever below the floor by more than the thickness.
    - At rest by 3 s: over the last 1/4 s the centre of mass moves slower than 2 cm/s and the
      kinetic energy (the integrator's own velocities) stays below 1e-4 m g h.
    Also times steps per second with and without the floor.
    """
    height, thickness = 1.0, 0.02
    body = build_body((0.2, 0.2, 0.2), (4, 4, 4), 2e4, offset=np.array([-0.1, -0.1, height]))
    floor = quad([[-5, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0]], thickness=thickness,
                 damping=0.5)
    _, beta = dynamics.rayleigh_from_damping_ratio(0.05, body["omega"][0], 1.0)
    kinetic = []
    con = body_contact(body, [floor])
    sim = dynamics.Simulation(body["deformer"], body["X"], body["masses"], body["potential"],
                              1.0 / FPS, gravity=GRAVITY, free=True, stiffness_damping=beta,
                              contact=con, substeps=SUB)
    start = time.perf_counter()
    trajectory = sim.run(3 * FPS, callback=lambda *_: kinetic.append(sim.energy()["kinetic"]))
    seconds = time.perf_counter() - start
    _, free_sim, free_seconds = simulate(body, None, 3 * FPS, gravity=GRAVITY, free=True,
                                         stiffness_damping=beta, substeps=SUB)
    t = trajectory.times
    com = centre_of_mass(body, trajectory)
    fall = np.abs(com[:, 2] - (com[0, 2] - 0.5 * G * t ** 2))
    touched = int(np.argmax(fall > 1e-9))
    samples = trajectory.world_positions(body["X"][body["idx"]], body["rows"])
    lowest = samples[:, :, 2].min()
    mgh = body["masses"].sum() * G * height
    late = t >= 3.0 - 0.25 - 1e-9
    speed = np.linalg.norm(np.diff(com[late], axis=0), axis=1).max() * FPS
    late_kinetic = max(kinetic[-int(0.25 * FPS):])
    rebound = np.diff(com[touched - 1:, 2]).max() * FPS / (G * np.sqrt(2 * height / G))
    elastic = np.abs(trajectory.body_displacements(body["deformer"].basis)).max(axis=(1, 2))
    steps = 3 * FPS * sim.substeps
    print(f"drop 1 m: contact starts in the frame ending at {t[touched]:.4f} s (sqrt(2h/g) = "
          f"{np.sqrt(2 * height / G):.4f} s); largest upward frame velocity after it "
          f"{rebound:.2f} of the impact speed; lowest sample {1e3 * lowest:+.2f} mm (thickness "
          f"{1e3 * thickness:.0f} mm); last 0.25 s: com speed <= {100 * speed:.3f} cm/s, kinetic "
          f"<= {late_kinetic / mgh:.1e} m g h; rests {1e3 * samples[-1, :, 2].min():.1f} mm above "
          f"the floor; largest elastic displacement {1e3 * elastic.max():.1f} mm (at "
          f"{t[np.argmax(elastic)]:.2f} s), {1e3 * elastic[-1]:.1f} mm at rest; beta {beta:.2e} s; {steps / seconds:.0f} "
          f"steps/s with the floor, {steps / free_seconds:.0f} without "
          f"({trajectory.iterations.sum()} / {3 * FPS} Newton iterations)")
    assert touched > 0 and abs(t[touched] - np.sqrt(2 * height / G)) <= 1.0 / FPS
    assert samples[:touched, :, 2].min() > thickness      # nothing touched before
    assert lowest > -thickness
    assert speed < 0.02 and late_kinetic < 1e-4 * mgh


def test_undamped_drop_gains_no_energy(monkeypatch):
    """The cube of the drop test dropped 1 m onto a floor without damping, friction or material
    damping, one step per frame: kinetic + elastic + gravity (the barrier's own energy left out,
    it is >= 0) never exceeds its start value by more than 1e-3 m g h, and the centre of mass
    never climbs back above its start. With the contact force carried in Newmark's acceleration
    (``STABILISED_CONTACT = False``) the same drop gains energy and climbs above its start."""
    height = 1.0
    body = build_body((0.2, 0.2, 0.2), (4, 4, 4), 2e4, offset=np.array([-0.1, -0.1, height]))
    floor = quad([[-5, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0]], damping=0.0)
    mgh = body["masses"].sum() * G * height
    results = {}
    for stabilised in (True, False):
        monkeypatch.setattr(integrators, "STABILISED_CONTACT", stabilised)
        con = body_contact(body, [floor])
        sim = dynamics.Simulation(body["deformer"], body["X"], body["masses"], body["potential"],
                                  1.0 / FPS, gravity=GRAVITY, free=True, contact=con)
        energies = [sim.energy()["total"]]
        trajectory = sim.run(2 * FPS, callback=lambda *_: energies.append(sim.energy()["total"]))
        com = centre_of_mass(body, trajectory)
        results[stabilised] = ((max(energies) - energies[0]) / mgh, com[:, 2].max() - com[0, 2],
                               np.diff(com[:, 2]).max() * FPS / np.sqrt(2 * G * height))
    print("undamped drop: " + "; ".join(
        f"{'stabilised' if k else 'carried'}: energy rise {v[0]:+.2e} m g h, highest centre "
        f"{v[1]:+.3f} m from the start, largest upward frame velocity {v[2]:.2f} of the impact "
        f"speed" for k, v in results.items()))
    assert results[True][0] <= 1e-3 and results[True][1] <= 1e-9
    assert results[False][0] > 0.1 and results[False][1] > 0.0


# 2. A box on a 30 degree slope ---------------------------------------------------------------

@pytest.fixture(scope="module")
def slope():
    """A 0.2 m box (4^3 cells, E = 2e5 Pa, 8 kg) resting on its face on a plane tilted 30 deg
    about y, its bottom 1.9 cm (0.95 thickness) above it; along = down-slope unit vector."""
    tilt = Rotation.from_rotvec([0.0, -np.radians(30.0), 0.0]).as_matrix()
    normal = tilt @ np.array([0.0, 0.0, 1.0])
    body = build_body((0.2, 0.2, 0.2), (4, 4, 4), 2e5, rotation=tilt,
                      offset=tilt @ np.array([-0.1, -0.1, 0.0]) + 0.019 * normal)
    corners = np.array([[-3, -3, 0], [3, -3, 0], [3, 3, 0], [-3, 3, 0]], float) @ tilt.T
    return dict(body=body, corners=corners, normal=normal,
                along=-tilt @ np.array([1.0, 0.0, 0.0]))


@pytest.mark.parametrize("integrator", ["newmark", "implicit_euler"])
def test_frictionless_box_slides_at_g_sin_30(slope, integrator):
    """A box rather than a sphere: with friction a sphere rolls, so only a sliding block can
    show that mu > tan 30 holds it. Friction 0: the centre of mass accelerates along the slope
    at g sin 30 (least-squares fit of 1/2 a t^2 + v t + x0 over 1 s) within 5 %, with either
    integrator (implicit Euler's recursion only adds a velocity-like 1/2 a dt t)."""
    body = slope["body"]
    plane = quad(slope["corners"], friction=0.0)
    trajectory, sim, _ = simulate(body, [plane], FPS, gravity=GRAVITY, free=True,
                                  integrator=integrator)
    t = trajectory.times
    down = (centre_of_mass(body, trajectory) - centre_of_mass(body, trajectory)[0]) @ slope["along"]
    fit = np.linalg.lstsq(np.stack([0.5 * t ** 2, t, np.ones_like(t)], axis=1), down,
                          rcond=None)[0]
    samples = trajectory.world_positions(body["X"][body["idx"]], body["rows"])
    gap = ((samples - slope["corners"][0]) @ slope["normal"]).min()
    print(f"frictionless slope, {integrator}: acceleration {fit[0]:.4f} m/s^2, g sin 30 = {G / 2:.4f} "
          f"({100 * (fit[0] / (G / 2) - 1):+.2e} %); slid {down[-1]:.3f} m in 1 s; closest "
          f"sample {1e3 * gap:.1f} mm from the plane")
    assert abs(fit[0] / (G / 2) - 1.0) <= 0.05
    assert 0.0 < gap < 0.02


def test_box_with_friction_one_stays_on_the_slope(slope):
    """Friction 1.0 > tan 30 = 0.577: over 1 s the samples touching the plane (in its band at
    the end) slide less than 2 mm along it (the smoothed Coulomb law creeps below EPS_V =
    1 mm/s), against 2.45 m without friction; the centre of mass moves less than 5 mm (the
    box's elastic shear settles it a little)."""
    body = slope["body"]
    plane = quad(slope["corners"], friction=1.0)
    trajectory, _, _ = simulate(body, [plane], FPS, gravity=GRAVITY, free=True)
    samples = trajectory.world_positions(body["X"][body["idx"]], body["rows"])
    touching = ((samples[-1] - slope["corners"][0]) @ slope["normal"]) < 0.02
    slide = ((samples[-1, touching] - samples[0, touching]) @ slope["along"]).mean()
    com = centre_of_mass(body, trajectory)
    com_move = np.linalg.norm(com - com[0], axis=1).max()
    print(f"slope with friction 1: {touching.sum()} samples touching slid {1e3 * slide:+.2f} mm "
          f"in 1 s; centre of mass moved at most {1e3 * com_move:.2f} mm")
    assert touching.sum() >= 4
    assert abs(slide) < 0.002
    assert com_move < 0.005


# 3. A keyed bar swinging into a wall -----------------------------------------------------------

def test_keyed_bar_stops_at_the_wall():
    """A 1 x 0.1 x 0.1 m bar (20 x 2 x 2 cells, E = 1e7 Pa) pinned at x = 0 on a frame keyed to
    turn 60 deg about z in 1 s (then held); a static wall quad at y = 0.5 m facing the bar,
    spanning x in [0.75, 1.4] (thickness 2 cm, damping 0.5). Without the wall the tip passes
    y = 0.5 (it reaches sin 60 = 0.87); with it no sample ever gets behind the wall, and the
    tip ends held in the wall's band."""
    body = build_body((1.0, 0.1, 0.1), (20, 2, 2), 1e7, pinned=True, samples=80)
    y_wall, thickness = 0.5, 0.02
    wall = quad([[0.75, y_wall, -0.5], [1.4, y_wall, -0.5], [1.4, y_wall, 0.5],
                 [0.75, y_wall, 0.5]], thickness=thickness)
    assert wall.surface(0.0).face_normal[0] @ np.array([0.0, 1.0, 0.0]) < 0.0   # faces the bar
    motion = frames.FrameMotion([0.0, 1.0], Rotation.from_rotvec(
        [[0, 0, 0], [0, 0, np.radians(60.0)]]).as_matrix(), np.zeros((2, 3)))
    runs = {}
    for name, colliders in (("wall", [wall]), ("none", None)):
        trajectory, _, seconds = simulate(body, colliders, int(1.5 * FPS), frame_motion=motion,
                                          stiffness_damping=0.002)
        runs[name] = trajectory.world_positions(body["X"][body["idx"]], body["rows"]), seconds
    tip = body["X"][body["idx"], 0] > 1.0 - 1e-9
    reach = {name: y[:, tip, 1].max() for name, (y, _) in
             ((k, (v[0], None)) for k, v in runs.items())}
    behind = runs["wall"][0][:, :, 1].max()
    held = y_wall - runs["wall"][0][-1, tip, 1].max()
    print(f"keyed bar: tip reaches y = {reach['none']:.3f} m without the wall; with it every "
          f"sample stays below y = {behind:.4f} m (wall {y_wall} m), the tip ends "
          f"{1e3 * held:.1f} mm from it ({runs['wall'][1]:.2f} s vs {runs['none'][1]:.2f} s)")
    assert reach["none"] > y_wall + 0.2
    assert behind < y_wall
    assert 0.0 < held < thickness
