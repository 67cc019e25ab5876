"""`make bench`: speed and memory of the solver, written as JSON plus a readable table.

Each case runs in its own child process so its peak memory (max RSS) is its own. Times are wall
clock on this machine; compare ratios within one run only.

    python bench/run_bench.py --output bench_output [--quick]
    python bench/run_bench.py --child pins box      # one case alone, its JSON row on stdout
    python bench/run_bench.py --farm                # the farm row alone
    python bench/run_bench.py --baseline REV --compare-only   # before/after rows alone
"""
import argparse
import json
import os
import pathlib
import platform
import resource
import subprocess
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
MESHES = ROOT.parent / "shared" / "data" / "meshes"

# 4:1:1 cantilevers, 6 tets per cell: 12k, 41k and 98k tets.
BAR_SIZES = {"10k": 8, "40k": 12, "100k": 16}


def peak_rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class StagePeak:
    """Peak RSS [MB] of one stage of a case: Linux's high-water mark (VmHWM) is reset on entry
    (``/proc/self/clear_refs``) and read on exit. Elsewhere it is the process's peak so far."""

    def __enter__(self):
        try:
            pathlib.Path("/proc/self/clear_refs").write_text("5")
        except OSError:
            pass
        return self

    def __exit__(self, *exc):
        self.mb = peak_rss_mb()
        try:
            for line in pathlib.Path("/proc/self/status").read_text().splitlines():
                if line.startswith("VmHWM:"):
                    self.mb = int(line.split()[1]) / 1024.0
        except OSError:
            pass
        return False


def read_surface(path):
    import igl
    if path.suffix == ".mesh":          # a MEDIT tet mesh: tetrahedralise its surface anew
        V, _, F = igl.readMESH(str(path))
        return V, F
    V, F = igl.read_triangle_mesh(str(path))[:2]
    return V, F


def _children_cpu_seconds():
    """User + system CPU seconds of this process's finished children (the fTetWild worker)."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def case_tetrahedralize(name):
    """fTetWild as Prepare runs it at the default settings on a shared mesh or ``knight256k``
    (``prepare_surface``): the proxy (when the surface has more triangles than its budget), then
    the worker. Wall and CPU seconds (CPU is steadier on a loaded machine), the tets and their
    smallest dihedral angle, and the panel's estimate for the surface fTetWild meshed (the
    inputs of ``mesher_fit``)."""
    import numpy as np
    from solver import preparation, proxy, tetmesh
    V, F = prepare_surface(name)
    meshing = preparation.MeshingSettings()
    start = time.perf_counter()
    P, G, closed = preparation.mesher_surface(V, F, meshing)
    proxy_seconds = time.perf_counter() - start
    cpu, start = _children_cpu_seconds(), time.perf_counter()
    X, T = preparation.tet_mesh(P, G, meshing)
    seconds, cpu = time.perf_counter() - start, _children_cpu_seconds() - cpu
    quality = getattr(tetmesh, "min_dihedral_angles", None)     # absent in older revisions
    angles = quality(X, T) if quality else np.full(1, np.nan)
    thin = getattr(proxy, "surface_thinness", None)
    thinness = thin(P, G, meshing.edge_length) if thin else 1.0
    estimate = proxy.tetwild_seconds(len(G), thinness) if thin else proxy.tetwild_seconds(len(G))
    return dict(mesh=name, surface_vertices=len(V), surface_faces=len(F), meshed_faces=len(G),
                thinness=thinness, nodes=len(X), tets=len(T), proxy_seconds=proxy_seconds,
                seconds=seconds, cpu_seconds=cpu, estimate_seconds=estimate,
                min_dihedral=float(angles.min()), below_10_degrees=float(np.mean(angles < 10.0)))


# fTetWild's CPU seconds (user + system, its threads summed) on the shared meshes with the shipped
# defaults, as `--child tetrahedralize NAME` measured them (meshed triangles, seconds). CPU time
# is what the estimate is fitted to: wall time on this shared 2-core machine was 3-15x the CPU
# time while other work ran, and on an idle machine with n cores fTetWild's threads make the
# wall time at most the CPU time. Refit after a change of defaults: measure each mesh once, put
# the rows here, `--child mesher_fit recorded`, and copy the fit to proxy.TETWILD_SECONDS.
# The first four: the shipped defaults (one run each, load ~17). The rest widen the triangle
# range: fTetWild's own defaults (stop energy 10, 80 passes) on the whole surface or the old,
# finer proxy, and the 12-triangle box of tests/solver/test_pins.py at edge 0.0198.
MESHER_MEASURED = [
    dict(mesh="spot.obj", meshed_faces=1500, thinness=0.982, cpu_seconds=1.81),
    dict(mesh="cow.off", meshed_faces=1500, thinness=1.202, cpu_seconds=4.45),
    dict(mesh="decimated-knight.off", meshed_faces=1000, thinness=2.01, cpu_seconds=4.73),
    dict(mesh="octopus-low.mesh", meshed_faces=898, thinness=4.033, cpu_seconds=8.95),
    dict(mesh="spot.obj whole", meshed_faces=5856, thinness=1.029, cpu_seconds=8.83),
    dict(mesh="cow.off whole", meshed_faces=5520, thinness=1.295, cpu_seconds=16.69),
    dict(mesh="spot.obj old proxy", meshed_faces=3150, thinness=1.03, cpu_seconds=3.81),
    dict(mesh="box bar", meshed_faces=12, thinness=0.84, cpu_seconds=1.2),
]
# Not in the fit: knight256k's smooth 1,500-triangle proxy (thinness 1.83) took 1.66 CPU s, which
# the fit overestimates 3x (4.9 s): sharp features, not thinness alone, keep fTetWild busy.


def mesher_fit(rows):
    """(a [s], b [s per triangle]) of CPU seconds = thinness x (a + b x meshed triangles)
    through the rows' (meshed_faces, thinness, cpu_seconds), least squares in the relative
    error, a, b >= 0: the panel's estimate (``proxy.TETWILD_SECONDS``)."""
    import numpy as np
    from scipy.optimize import lsq_linear
    n = np.array([r["meshed_faces"] for r in rows], dtype=float)
    t = np.array([r.get("thinness", 1.0) for r in rows], dtype=float)
    s = np.array([r["cpu_seconds"] for r in rows], dtype=float)
    design = np.column_stack([t, t * n]) / s[:, None]
    fit = lsq_linear(design, np.ones_like(s), bounds=([0.0, 0.0], np.inf))
    return float(fit.x[0]), float(fit.x[1])


def case_mesher_fit(arg):
    """The fit of MESHER_MEASURED ("recorded") and each row's fitted / measured CPU seconds."""
    a, b = mesher_fit(MESHER_MEASURED)
    fitted = [r["thinness"] * (a + b * r["meshed_faces"]) for r in MESHER_MEASURED]
    return dict(fit=[a, b], rows=[dict(r, fitted=f, ratio=f / r["cpu_seconds"])
                                  for r, f in zip(MESHER_MEASURED, fitted)])


def tetrahedralize_table(rows):
    """Markdown: fTetWild per shared mesh, the estimate against the measurement, and this run's
    own fit (the estimate must be within 2x of the CPU seconds)."""
    good = [r for r in rows if "error" not in r]
    fit = mesher_fit(good) if len(good) >= 2 else (float("nan"), float("nan"))
    lines = ["## Tetrahedralisation as Prepare runs it (proxy, then fTetWild at the default "
             "settings: edge 0.05, envelope 1e-3)", "",
             "| mesh | faces | meshed | tets | min dihedral ° | < 10° | proxy s | fTetWild s "
             "| CPU s | estimate s | estimate / CPU | estimate / wall |", "|" + "---|" * 12]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['arg']} | error: {r['error']} |")
            continue
        estimate, below_10 = r["estimate_seconds"], 100 * r["below_10_degrees"]
        lines.append(f"| {r['mesh']} | {r['surface_faces']:,} | {r['meshed_faces']:,} "
                     f"| {r['tets']:,} | {r['min_dihedral']:.1f} | {below_10:.2f} % "
                     f"| {r['proxy_seconds']:.2f} | {r['seconds']:.2f} | {r['cpu_seconds']:.2f} "
                     f"| {estimate:.1f} | {estimate / r['cpu_seconds']:.2f} "
                     f"| {estimate / r['seconds']:.2f} |")
    lines += ["", f"This run's fit (``mesher_fit``, CPU seconds): thinness x ({fit[0]:.2f} s + "
              f"{1000 * fit[1]:.3f} ms per meshed triangle)."]
    return "\n".join(lines) + "\n"


PREPARE_MESHES = {"cow": "cow.off", "spot": "spot.obj", "knight256k": "decimated-knight.off"}


def prepare_surface(name):
    """(V, F) of a Prepare case: a shared mesh, or ``knight256k``, the knight upsampled 4 times
    (256k triangles)."""
    import igl
    import numpy as np
    V, F = read_surface(MESHES / PREPARE_MESHES.get(name, name))
    V, F = np.asarray(V, float), np.asarray(F, np.int64)
    if name == "knight256k":
        V, F = igl.upsample(V, F, number_of_subdivs=4)[:2]
    return V, F


def prepare_stages(V, F):
    """Prepare at the default settings (edge 0.05, 20 modes, automatic basis and cubature, a free
    body) of the surface (V, F), stage by stage as Prepare Body runs them
    (``solver.preparation``): the row of ``case_prepare``."""
    import numpy as np
    from solver import preparation
    seconds, peaks = {}, {}

    def stage(name, work):
        start = time.perf_counter()
        with StagePeak() as peak:
            out = work()
        seconds[name], peaks[name] = time.perf_counter() - start, peak.mb
        return out

    meshing = preparation.MeshingSettings()
    P, G, closed = stage("proxy", lambda: preparation.mesher_surface(V, F, meshing))
    X, T = stage("tetrahedralize", lambda: preparation.tet_mesh(P, G, meshing))
    tet_body = stage("embed", lambda: preparation.embedded(X, T, V))
    if hasattr(preparation, "deformer_at"):     # the stages at 1 Pa and 1 kg/m^3, as Prepare
        unit = stage("modes", lambda: preparation.unit_stiffness_modes(tet_body, 0.45, 20))
        deformer = stage("reduced", lambda: preparation.reduced_deformer(
            tet_body, unit, preparation.ReducedSettings()))
    else:                                       # a solver before them (--baseline)
        linear = stage("modes", lambda: preparation.linear_modes(tet_body, 1e6, 0.45, 1000.0, 20))
        deformer = stage("reduced", lambda: preparation.reduced_deformer(
            tet_body, linear, 1000.0, preparation.ReducedSettings()))
    return dict(triangles=len(F), proxy_triangles=len(G), simplified=closed and len(G) < len(F),
                nodes=len(X), tets=len(T), basis_size=deformer.basis_size,
                cubature_tets=len(deformer.cubature_tets), seconds=seconds,
                stage_peak_rss_mb=peaks, total_seconds=sum(seconds.values()),
                mesher_seconds=seconds["proxy"] + seconds["tetrahedralize"],
                peak_rss_mb=peak_rss_mb())


def case_prepare(name):
    """Prepare end to end at the default settings of cow, spot or knight256k (targets: cow and
    spot < 10 s, knight256k < 15 s)."""
    return dict(prepare_stages(*prepare_surface(name)), mesh=name)


def case_prepare_dense(subdivisions):
    """``prepare_stages`` of the shared knight upsampled ``subdivisions`` times (4: 256k
    triangles)."""
    import igl
    import numpy as np
    V, F = read_surface(MESHES / "decimated-knight.off")
    V, F = igl.upsample(np.asarray(V, float), np.asarray(F, np.int64),
                        number_of_subdivs=int(subdivisions))[:2]
    return prepare_stages(V, F)


def prepare_table(rows):
    """Markdown: Prepare end to end per mesh, the mesher's share (proxy + fTetWild) apart."""
    lines = ["## Prepare end to end at the default settings (free body, 20 modes; targets: cow "
             "and spot < 10 s, knight256k < 15 s)", "",
             "| mesh | triangles | proxy | tets | rB | cubature | mesher s | embed s | modes s "
             "| reduced s | total s | peak RSS MB |", "|" + "---|" * 12]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['arg']} | error: {r['error']} |")
            continue
        t = r["seconds"]
        lines.append(f"| {r['mesh']} | {r['triangles']:,} | {r['proxy_triangles']:,} "
                     f"| {r['tets']:,} | {r['basis_size']} | {r['cubature_tets']} "
                     f"| {r['mesher_seconds']:.1f} | {t['embed']:.1f} | {t['modes']:.1f} "
                     f"| {t['reduced']:.1f} | {r['total_seconds']:.1f} | {r['peak_rss_mb']:.0f} |")
    return "\n".join(lines) + "\n"


def prepare_dense_table(row):
    lines = ["## Prepare a dense surface at the default settings (knight upsampled to 256k "
             "triangles, free body; targets < 60 s, < 2 GB)", "",
             "| triangles | proxy | nodes | tets | rB | cubature | proxy s | fTetWild s | embed s "
             "| modes s | reduced s | total s | peak RSS MB |", "|" + "---|" * 13]
    if "error" in row:
        lines.append(f"| error: {row['error']} |")
    else:
        t = row["seconds"]
        lines.append(f"| {row['triangles']:,} | {row['proxy_triangles']:,} | {row['nodes']:,} "
                     f"| {row['tets']:,} | {row['basis_size']} | {row['cubature_tets']} "
                     f"| {t['proxy']:.1f} | {t['tetrahedralize']:.1f} | {t['embed']:.1f} "
                     f"| {t['modes']:.1f} | {t['reduced']:.1f} | {row['total_seconds']:.1f} "
                     f"| {row['peak_rss_mb']:.0f} |")
        lines += ["", "Peak RSS of each stage (MB): " + ", ".join(
            f"{name} {mb:.0f}" for name, mb in row["stage_peak_rss_mb"].items())]
    return "\n".join(lines) + "\n"


def _bar_problem(size):
    import numpy as np
    from solver import fem, meshgen
    n = BAR_SIZES[size]
    X, T = meshgen.box_tet_mesh((4.0, 1.0, 1.0), (4 * n, n, n))
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    start = time.perf_counter()
    K = fem.stiffness_matrix(X, T, 1e6, 0.45)
    m = fem.lumped_masses(X, T, 1100.0)
    return X, T, pinned, K, m, time.perf_counter() - start


def case_modes(arg):
    """20 modes of the pinned bar; arg "<size>" (SuperLU's minimum degree, the first solver),
    "<size>:nd" (SuperLU in nested-dissection order, solver.ordering) or "<size>:chol" (the
    supernodal Cholesky on the same nested dissection, solver.cholesky; the default). Peak RSS
    of the modes stage alone."""
    from solver import modes
    size, _, kind = arg.partition(":")
    factorisation = {"nd": "superlu_nd", "chol": "supernodal"}.get(kind, "superlu_mmd")
    X, T, pinned, K, m, assembly = _bar_problem(size)
    baseline = peak_rss_mb()
    start = time.perf_counter()
    with StagePeak() as peak:
        result = modes.linear_modes(K, m, 20, pinned, rest_positions=X, factorisation=factorisation)
    mode_seconds = time.perf_counter() - start
    return dict(size=size, factorisation=factorisation, nodes=len(X), tets=len(T),
                assembly_seconds=assembly, modes_seconds=mode_seconds, num_modes=20,
                first_frequency_hz=float(result.frequencies_hz[0]), modes_peak_rss_mb=peak.mb,
                peak_rss_mb=peak_rss_mb(), rss_before_mb=baseline)


def case_modes_agreement(size):
    """Old (SuperLU, minimum degree) and new (supernodal Cholesky, nested dissection) modes of one
    bar: the largest relative eigenvalue difference and the largest principal angle between the
    two 20-mode subspaces (M inner product)."""
    import numpy as np
    import scipy.linalg
    from solver import modes
    X, T, pinned, K, m, _ = _bar_problem(size)
    old, new = (modes.linear_modes(K, m, 20, pinned, rest_positions=X, factorisation=f)
                for f in ("superlu_mmd", "supernodal"))
    w = np.sqrt(np.repeat(m, 3))[:, None]
    cosines = scipy.linalg.svdvals(np.linalg.qr(w * old.vectors)[0].T
                                   @ np.linalg.qr(w * new.vectors)[0])
    return dict(size=size, tets=len(T),
                max_relative_eigenvalue_difference=float(
                    np.max(np.abs(new.eigenvalues - old.eigenvalues) / old.eigenvalues)),
                max_principal_angle=float(np.arccos(np.clip(cosines.min(), -1.0, 1.0))))


def case_rs_full(size, repeats=5):
    """Full RS reconstruction on a pinned bar: factorisation, then y -> u (median of repeats).

    Pose: the first bending mode warped with a linear tip displacement of 8x the thickness.
    """
    import numpy as np
    from solver import fem, meshgen, modes, rs
    n = BAR_SIZES[size]
    X, T = meshgen.box_tet_mesh((4.0, 1.0, 1.0), (4 * n, n, n))
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    K = fem.stiffness_matrix(X, T, 1e6, 0.45)
    W = modes.linear_modes(K, fem.lumped_masses(X, T, 1100.0), 1, pinned,
                           rest_positions=X).vectors
    tip = X[:, 0] > 4.0 - 1e-9
    amplitude = 8.0 / np.linalg.norm(W.reshape(len(X), 3, 1)[tip].mean(axis=0))
    y = rs.warp_modes(rs.linear_rs(rs.rs_operator(X, T), W), [amplitude])
    baseline = peak_rss_mb()
    start = time.perf_counter()
    recon = rs.PoissonReconstruction(X, T, pinned)
    factor_seconds = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        u = recon.reconstruct(y)
        times.append(time.perf_counter() - start)
    return dict(size=size, nodes=len(X), tets=len(T), factor_seconds=factor_seconds,
                reconstruct_seconds=float(np.median(times)), repeats=repeats,
                volume_ratio=rs.volume(X, T, X + u) / rs.volume(X, T, X),
                peak_rss_mb=peak_rss_mb(), rss_before_mb=baseline)


CASES = {"tetrahedralize": case_tetrahedralize, "modes": case_modes,
         "modes_agreement": case_modes_agreement, "rs_full": case_rs_full,
         "prepare_dense": case_prepare_dense, "prepare": case_prepare,
         "mesher_fit": case_mesher_fit}


def _median_seconds(function, number, repeat=15):
    """Median over ``repeat`` runs of the mean time of ``number`` calls, in seconds."""
    import timeit
    return float(sorted(timeit.repeat(function, number=number, repeat=repeat))[repeat // 2]
                 / number)


def case_reduced_rs(size, num_modes=20, num_held_out=40):
    """Reduced RS with cubature on the pinned bar of ``rs_full`` (20 modes), default settings.

    Preparation (``reduced.prepare_reduced_rs``: snapshots, basis, cubature) is timed once.
    Evaluations are medians of many calls for one held-out pose (its largest rotation):
    the whole surface (rows of B for the boundary nodes, precomputed), 10 surface vertices
    (folded rows), their Jacobian, and both together; full RS is recon.reconstruct(QW z) with
    the prefactored Laplacian, timed in the same process. Error: 40 held-out poses (seed not
    used in training, rotations up to 90 deg, strain <= 100 %), max vertex error / diagonal.
    BLAS runs on one thread in this child (set before numpy loads): the reduced path is many
    small products, which lose several-fold to thread hand-offs when the cores are shared,
    and full RS's sparse solve is single-threaded anyway, so both get one core.
    """
    import os
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    import igl
    import numpy as np
    from solver import cubature, fem, meshgen, modes, reduced, rs
    n = BAR_SIZES[size]
    X, T = meshgen.box_tet_mesh((4.0, 1.0, 1.0), (4 * n, n, n))
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    masses = fem.lumped_masses(X, T, 1100.0)
    body = modes.linear_modes(fem.stiffness_matrix(X, T, 1e6, 0.45), masses, num_modes, pinned,
                              rest_positions=X)
    start = time.perf_counter()
    modal_rs = rs.linear_rs(rs.rs_operator(X, T), body.vectors)
    recon = rs.PoissonReconstruction(X, T, pinned)
    setup_seconds = time.perf_counter() - start
    baseline = peak_rss_mb()
    start = time.perf_counter()
    deformer, info = reduced.prepare_reduced_rs(X, T, masses, body.vectors, body.eigenvalues,
                                                recon, modal_rs=modal_rs)
    prepare_seconds = time.perf_counter() - start

    surface = np.unique(igl.boundary_facets(T)[0])
    surface_rows = reduced.basis_rows(deformer.basis, surface)
    few = reduced.basis_rows(deformer.basis, np.random.default_rng(0).choice(surface, 10, False))
    evaluator = deformer.row_evaluator(few)
    Z = cubature.training_poses(num_modes, body.eigenvalues, num_held_out,
                                np.random.default_rng(1234), max_rotation=np.pi / 2,
                                modal_rs=modal_rs)
    rotation, _ = cubature.pose_extremes(modal_rs, Z)
    z = Z[int(np.argmax(rotation))]
    timings = dict(
        surface_seconds=_median_seconds(lambda: deformer.displacement(z, rows=surface_rows), 50),
        few_seconds=_median_seconds(lambda: evaluator.displacement(z), 200),
        jacobian_seconds=_median_seconds(lambda: evaluator.jacobian(z), 100),
        few_and_jacobian_seconds=_median_seconds(lambda: evaluator.evaluate(z), 100),
        full_seconds=_median_seconds(lambda: recon.reconstruct(modal_rs @ z), 1, repeat=9))
    diagonal = float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))
    errors = np.array([np.linalg.norm(deformer.displacement(p) - recon.reconstruct(modal_rs @ p),
                                      axis=1).max() / diagonal for p in Z])
    return dict(size=size, nodes=len(X), tets=len(T), num_modes=num_modes,
                basis_size=deformer.basis_size, cubature_tets=len(deformer.cubature_tets),
                fit_residual=info["relative_residual"], setup_seconds=setup_seconds,
                prepare_seconds=prepare_seconds, snapshot_seconds=info["seconds"]["snapshots"],
                basis_seconds=info["seconds"]["basis"],
                cubature_seconds=info["seconds"]["cubature"], surface_vertices=len(surface),
                **timings,
                speedup_few_and_jacobian=timings["full_seconds"]
                / timings["few_and_jacobian_seconds"],
                speedup_surface=timings["full_seconds"] / timings["surface_seconds"],
                max_rotation_deg=float(np.degrees(rotation.max())),
                max_error=float(errors.max()), mean_error=float(errors.mean()),
                peak_rss_mb=peak_rss_mb(), rss_before_mb=baseline)


def reduced_rs_table(rows):
    """Markdown table of ``case_reduced_rs`` rows (times shown in µs / ms, errors in %)."""
    shown = []
    for row in rows:
        if "error" not in row:
            row = dict(row, full_ms=1e3 * row["full_seconds"], max_error_pct=100 * row["max_error"],
                       mean_error_pct=100 * row["mean_error"],
                       **{key + "_us": 1e6 * row[key + "_seconds"]
                          for key in ("surface", "few", "jacobian", "few_and_jacobian")})
        shown.append(row)
    return table(
        "Reduced RS with cubature (pinned 4:1:1 bar, 20 modes; targets: 10 vertices + Jacobian "
        ">= 100x faster than full RS at 40k tets, held-out error <= 1 % of the diagonal, "
        "preparation < 60 s at 40k)", shown,
        [("size", ("size", "{}")), ("tets", ("tets", "{:,}")), ("rB", ("basis_size", "{}")),
         ("cubature tets", ("cubature_tets", "{}")), ("prepare s", ("prepare_seconds", "{:.1f}")),
         ("snapshots s", ("snapshot_seconds", "{:.1f}")), ("basis s", ("basis_seconds", "{:.1f}")),
         ("cubature s", ("cubature_seconds", "{:.1f}")),
         ("surface verts", ("surface_vertices", "{:,}")), ("surface µs", ("surface_us", "{:.0f}")),
         ("10 verts µs", ("few_us", "{:.0f}")), ("Jacobian (10) µs", ("jacobian_us", "{:.0f}")),
         ("10 verts + Jacobian µs", ("few_and_jacobian_us", "{:.0f}")),
         ("full RS ms", ("full_ms", "{:.2f}")),
         ("speed-up 10 + J", ("speedup_few_and_jacobian", "{:.0f}x")),
         ("speed-up surface", ("speedup_surface", "{:.0f}x")),
         ("held-out max error %", ("max_error_pct", "{:.2f}")),
         ("mean error %", ("mean_error_pct", "{:.2f}")),
         ("max rotation deg", ("max_rotation_deg", "{:.0f}")),
         ("peak RSS MB", ("peak_rss_mb", "{:.0f}"))])


CASES["reduced_rs"] = case_reduced_rs


CUBATURE_ROWS = ("10k:20", "10k:40", "40k:20", "40k:40")


def case_cubature(arg, num_held_out=40):
    """The reduced RS cubature's training time and held-out error; arg "<size>:<modes>" or
    "<size>:<modes>:<seeds>".

    The pinned bar of ``rs_full`` with ``reduced.prepare_reduced_rs`` at its defaults (the
    automatic basis and cubature sizes grow with the modes); ``cubature_seconds`` is its
    cubature stage (training poses, the exact fit of the training poses, the greedy NNLS and
    the deformer). BLAS keeps its default threads (the stage's work is its own threads; one
    BLAS thread, as a Prepare in Blender runs, measured the same here). Error: the held-out
    poses of ``reduced_rs`` (seed not used in training, rotations up to 90 deg, strain
    <= 100 %), max vertex error over the diagonal, for the deformer and for the all-tet fit
    on the same basis (no cubature: the floor the cubature can reach). With <seeds> the
    preparation is repeated with seeds 1 .. seeds-1 too (``prepare_reduced_rs(seed=)``: its
    poses, hence its basis and its cubature, change with it) and ``seeds_*`` summarise the
    max error over all of them: one seed's max says little (the tets a greedy picks, and the
    basis, move it by a third either way). Only names that already existed before this case
    are called, so it runs against an older solver too.
    """
    import numpy as np
    from solver import cubature, fem, modes, reduced, rs
    size, _, rest = arg.partition(":")
    count, _, seeds = rest.partition(":")
    num_modes, num_seeds = int(count or 20), int(seeds or 1)
    X, T, pinned, K, masses, _ = _bar_problem(size)
    body = modes.linear_modes(K, masses, num_modes, pinned, rest_positions=X)
    modal_rs = rs.linear_rs(rs.rs_operator(X, T), body.vectors)
    recon = rs.PoissonReconstruction(X, T, pinned)
    start = time.perf_counter()
    deformer, info = reduced.prepare_reduced_rs(X, T, masses, body.vectors, body.eigenvalues,
                                                recon, modal_rs=modal_rs)
    prepare_seconds = time.perf_counter() - start
    Z = cubature.training_poses(num_modes, body.eigenvalues, num_held_out,
                                np.random.default_rng(1234), max_rotation=np.pi / 2,
                                modal_rs=modal_rs)
    diagonal = float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))
    full = [recon.reconstruct(modal_rs @ z) for z in Z]

    def held_out(deformer):
        """(errors (poses,), all-tet floor (poses,)) of a deformer on the held-out poses."""
        return (np.array([np.linalg.norm(u - reference, axis=1).max() / diagonal
                          for u, reference in zip(values, full)])
                for values in ([deformer.displacement(z) for z in Z],
                               [(deformer.basis @ deformer.exact_q(z)).reshape(-1, 3)
                                for z in Z]))

    errors, floor = held_out(deformer)
    row = dict(size=size, tets=len(T), num_modes=num_modes, basis_size=deformer.basis_size,
               cubature_tets=len(deformer.cubature_tets),
               fit_residual=info["relative_residual"], prepare_seconds=prepare_seconds,
               basis_seconds=info["seconds"]["snapshots"] + info["seconds"]["basis"],
               cubature_seconds=info["seconds"]["cubature"],
               max_error=float(errors.max()), mean_error=float(errors.mean()),
               all_tet_max_error=float(floor.max()))
    if num_seeds > 1:
        maxima, means, floors = [row["max_error"]], [row["mean_error"]], [float(floor.max())]
        for seed in range(1, num_seeds):
            other, _ = reduced.prepare_reduced_rs(X, T, masses, body.vectors, body.eigenvalues,
                                                  recon, modal_rs=modal_rs, seed=seed)
            errors, floor = held_out(other)
            maxima.append(float(errors.max()))
            means.append(float(errors.mean()))
            floors.append(float(floor.max()))
        row.update(seeds=num_seeds, seeds_max_errors=maxima,
                   seeds_mean_of_max=float(np.mean(maxima)), seeds_worst_max=float(np.max(maxima)),
                   seeds_mean_error=float(np.mean(means)), seeds_all_tet_max_errors=floors)
    return dict(row, peak_rss_mb=peak_rss_mb())


def cubature_table(rows):
    """Markdown table of ``case_cubature`` rows (errors in % of the diagonal)."""
    shown = [row if "error" in row else
             dict(row, max_error_pct=100 * row["max_error"], mean_error_pct=100 * row["mean_error"],
                  all_tet_max_error_pct=100 * row["all_tet_max_error"]) for row in rows]
    return table(
        "Reduced RS cubature training (pinned 4:1:1 bar, automatic basis and cubature; targets: "
        "cubature at 20 modes on 10k tets >= 10x faster than e08decd, Prepare of the 10k bar at "
        "40 modes < 30 s, held-out max error <= 0.33 % of the diagonal at 20 modes)", shown,
        [("size", ("size", "{}")), ("tets", ("tets", "{:,}")), ("modes", ("num_modes", "{}")),
         ("rB", ("basis_size", "{}")), ("cubature tets", ("cubature_tets", "{}")),
         ("cubature s", ("cubature_seconds", "{:.1f}")),
         ("snapshots + basis s", ("basis_seconds", "{:.1f}")),
         ("prepare s", ("prepare_seconds", "{:.1f}")), ("fit residual", ("fit_residual", "{:.2e}")),
         ("held-out max error %", ("max_error_pct", "{:.3f}")),
         ("mean error %", ("mean_error_pct", "{:.3f}")),
         ("all-tet fit max error %", ("all_tet_max_error_pct", "{:.3f}")),
         ("peak RSS MB", ("peak_rss_mb", "{:.0f}"))])


CASES["cubature"] = case_cubature


SPACETIME_MODES = ("10", "20", "40")
SPACETIME_FRAMES = (200, 400, 800)


def _edit_bar(num_modes, fractions):
    """The 10k-tet pinned 4:1:1 bar of the space-time cases (E = 1e6 Pa, nu = 0.45,
    1100 kg/m^3) with its reduced RS deformer, and handles at the cross-sections nearest the
    given fractions of its length. Returns (X, body, deformer, stations (k,), handles, arc):
    arc(s, angle) is the target of station s on the circular arc of that total angle."""
    import numpy as np
    from solver import fem, meshgen, modes, reduced, rs, spacetime
    n, length = BAR_SIZES["10k"], 4.0
    X, T = meshgen.box_tet_mesh((length, 1.0, 1.0), (4 * n, n, n))
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    masses = fem.lumped_masses(X, T, 1100.0)
    body = modes.linear_modes(fem.stiffness_matrix(X, T, 1e6, 0.45), masses, int(num_modes),
                              pinned)
    recon = rs.PoissonReconstruction(X, T, pinned)
    deformer, _ = reduced.prepare_reduced_rs(X, T, masses, body.vectors, body.eigenvalues, recon)
    planes = np.unique(X[:, 0])
    stations = planes[np.searchsorted(planes, length * np.asarray(fractions) - 1e-9)]
    handles = [spacetime.handle_geometry(X, deformer.basis,
                                         np.flatnonzero(np.abs(X[:, 0] - s) < 1e-9))
               for s in stations]

    def arc(s, angle):
        return np.array([np.sin(angle * s / length), 0.0, np.cos(angle * s / length) - 1.0]
                        ) * length / angle + [0.0, 0.5, 0.5]

    return X, body, deformer, stations, handles, arc


def case_spacetime(arg):
    """Space-time solves on the 10k-tet pinned bar with reduced RS; arg "MODES[:F1,F2,...]".

    Deformer: ``reduced.prepare_reduced_rs`` (basis + cubature, timed as setup). Edit: five
    handles (cross-sections at 1/5 ... 5/5 of the length, centroids) keyed onto the centre line
    bent into a 45 deg arc at 30 % and a 90 deg arc at 60 % of the range, free afterwards;
    gamma from ``suggest_weights``, h = 1/24 s. Each frame count is solved with and without
    material optimisation (default iterations). Stationarity: the decrease a GN step from the
    result still predicts, g^T H^-1 g / 2 over J (``_predicted_decrease``). Calls only names
    the solver had at e08decd, so the case runs against a baseline revision. numpy's BLAS
    runs on one thread (set before numpy loads), as a solve in Blender runs it
    (``bridge.jobs``: ``threads.one_blas_thread``).
    """
    import os
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    import numpy as np
    from solver import spacetime
    num_modes, _, frame_text = arg.partition(":")
    frame_counts = [int(f) for f in frame_text.split(",")] if frame_text else SPACETIME_FRAMES
    start = time.perf_counter()
    X, body, deformer, stations, handles, arc = _edit_bar(num_modes, np.arange(1, 6) / 5.0)
    setup = time.perf_counter() - start
    diagonal = float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))
    h = 1.0 / 24.0
    damping = spacetime.rayleigh_damping(body.eigenvalues, 0.1, 0.002)
    rows = []
    for frames in frame_counts:
        constraints = spacetime.HandleConstraints(
            frames=np.repeat([round(0.3 * frames), round(0.6 * frames)], 5),
            rows=[g[0] for g in handles] * 2, rest=[g[1] for g in handles] * 2,
            targets=[arc(s, a) for a in (np.pi / 4, np.pi / 2) for s in stations], weights=1.0)
        gamma, _ = spacetime.suggest_weights(h, body.eigenvalues, damping, deformer,
                                             constraints.rows)
        problem = spacetime.SpaceTimeProblem(frames, h, body.eigenvalues, damping, deformer,
                                             handles=constraints, gamma=gamma)
        for material in (False, True):
            start = time.perf_counter()
            result = spacetime.solve(problem, optimise_material=material)
            rows.append(dict(modes=int(num_modes), frames=frames, handles=5,
                             material="yes" if material else "no",
                             seconds=time.perf_counter() - start,
                             gn_iterations=result.iterations, converged=result.converged,
                             predicted_decrease=_predicted_decrease(problem, result),
                             residual=float(result.handle_residuals.max()) / diagonal,
                             control_energy=result.control_energy, scheme=problem.scheme,
                             setup_seconds=setup, basis_size=deformer.basis_size,
                             cubature_tets=len(deformer.cubature_tets),
                             peak_rss_mb=peak_rss_mb()))
    return dict(rows=rows)


def _predicted_decrease(problem, result):
    """g^T H^-1 g / (2 J) at the result: g, H the GN gradient and matrix of J in Z at the
    result's material (``spacetime.normal_equations``, banded)."""
    import scipy.linalg
    from solver import spacetime
    ab, g = spacetime.normal_equations(problem, result.Z, result.eigenvalues, result.damping,
                                       result.sampling)
    return 0.5 * float(g @ scipy.linalg.solveh_banded(ab, g, lower=True)) / result.objective


def spacetime_rows(quick):
    """Flattened solve rows of every mode count (--quick: 20 modes x 200 frames only)."""
    args = ["20:200"] if quick else list(SPACETIME_MODES)
    rows = []
    for arg in args:
        out = run_child("spacetime", arg)
        rows.extend([out] if "error" in out else out["rows"])
    return rows


def spacetime_table(rows):
    return table(
        "Space-time editing (10k-tet pinned bar, reduced RS, 5 handles keyed to a 90 deg bend; "
        "targets: 200 frames x 20 modes < 1 s without material, < 10 s with)", rows,
        [("modes", ("modes", "{}")), ("frames", ("frames", "{}")),
         ("material", ("material", "{}")), ("solve s", ("seconds", "{:.2f}")),
         ("GN steps", ("gn_iterations", "{}")), ("converged", ("converged", "{}")),
         ("GN decrease / J", ("predicted_decrease", "{:.0e}")),
         ("max residual / diagonal", ("residual", "{:.1e}")),
         ("E_f", ("control_energy", "{:.3e}")), ("scheme", ("scheme", "{}")),
         ("setup s", ("setup_seconds", "{:.1f}")), ("rB", ("basis_size", "{}")),
         ("cubature tets", ("cubature_tets", "{}")), ("peak RSS MB", ("peak_rss_mb", "{:.0f}"))])


CASES["spacetime"] = case_spacetime


LIVE_STEPS = (1, 2, 3)     # GN steps allowed to a warm live re-solve (bridge/live.py uses 3)


def case_live(arg, frames=100, repeats=7):
    """Warm live re-solve (bridge/live.py) on the 10k-tet bar, reduced RS; arg "MODES".

    Two handles (cross-sections at 3/5 and 5/5 of the length) keyed onto the 45 deg / 90 deg
    arcs of ``case_spacetime`` at 30 % and 60 % of 100 frames. A cold solve (default, with
    continuation) gives Z0; then the tip handle's 60 % target moves by 1 % of the diagonal and
    the edit is re-solved from Z0 with k GN steps and no continuation (median of ``repeats``).
    Quality: its objective against a full cold solve of the moved edit, and the tip's miss.
    """
    import numpy as np
    from solver import spacetime
    num_modes = int(arg)
    X, body, deformer, stations, handles, arc = _edit_bar(num_modes, [0.6, 1.0])
    diagonal = float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))
    h = 1.0 / 24.0
    damping = spacetime.rayleigh_damping(body.eigenvalues, 0.1, 0.002)
    targets = np.array([arc(s, a) for a in (np.pi / 4, np.pi / 2) for s in stations])

    def problem(targets):
        constraints = spacetime.HandleConstraints(
            frames=np.repeat([round(0.3 * frames), round(0.6 * frames)], 2),
            rows=[g[0] for g in handles] * 2, rest=[g[1] for g in handles] * 2,
            targets=targets, weights=1.0)
        gamma, _ = spacetime.suggest_weights(h, body.eigenvalues, damping, deformer,
                                             constraints.rows)
        return spacetime.SpaceTimeProblem(frames, h, body.eigenvalues, damping, deformer,
                                          handles=constraints, gamma=gamma)

    start = time.perf_counter()
    first = spacetime.solve(problem(targets))
    cold_seconds = time.perf_counter() - start
    moved = targets.copy()
    moved[3] += [0.0, 0.0, 0.01 * diagonal]        # the tip's 60 % target
    edited = problem(moved)
    start = time.perf_counter()
    reference = spacetime.solve(edited)
    reference_seconds = time.perf_counter() - start
    rows = []
    for steps in LIVE_STEPS:
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            warm = spacetime.solve(edited, iterations=steps, initial=first.Z,
                                   continuation=False)
            times.append(time.perf_counter() - start)
        rows.append(dict(modes=num_modes, frames=frames, handles=2, gn_steps=steps,
                         ms=1e3 * float(np.median(times)),
                         objective_ratio=warm.objective / reference.objective,
                         tip_miss=float(warm.handle_residuals[3]) / diagonal,
                         reference_miss=float(reference.handle_residuals[3]) / diagonal,
                         cold_seconds=cold_seconds, reference_seconds=reference_seconds,
                         reference_steps=reference.iterations))
    return dict(rows=rows)


def live_table(result):
    return table(
        "Live re-solve (bridge/live.py; 10k-tet bar, reduced RS, 100 frames x 2 handles, tip "
        "target moved by 1 % of the diagonal, warm start, no continuation; target < 33 ms)",
        result.get("rows", [result]),
        [("modes", ("modes", "{}")), ("GN steps", ("gn_steps", "{}")),
         ("re-solve ms", ("ms", "{:.1f}")), ("J / J full", ("objective_ratio", "{:.6f}")),
         ("tip miss / diag", ("tip_miss", "{:.1e}")),
         ("full solve miss / diag", ("reference_miss", "{:.1e}")),
         ("full solve s", ("reference_seconds", "{:.2f}")),
         ("full GN steps", ("reference_steps", "{}"))])


CASES["live"] = case_live


DYNAMICS_MODES = ("10", "20", "40", "20:100k")   # modes[:bar size], default the 10k bar


def _dynamics_body(num_modes, youngs=1e6, size="10k"):
    """A pinned 4:1:1 bar of the other cases (E = 1e6 Pa, nu = 0.45, 1100 kg/m^3), 10k by
    default."""
    import numpy as np
    from solver import fem, meshgen, modes, rs
    n = BAR_SIZES[size]
    X, T = meshgen.box_tet_mesh((4.0, 1.0, 1.0), (4 * n, n, n))
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    masses = fem.lumped_masses(X, T, 1100.0)
    body = modes.linear_modes(fem.stiffness_matrix(X, T, youngs, 0.45), masses, num_modes,
                              pinned)
    return X, T, pinned, masses, body, rs.PoissonReconstruction(X, T, pinned)


def _steps_per_second(simulation, warm_up, steps, blocks=3):
    """(steps/s, Newton iterations per step) after ``warm_up`` untimed steps: ``steps`` steps
    in ``blocks`` consecutive blocks, the fastest block's rate (like timeit's minimum, it
    discounts other load on the machine; the motion goes on from block to block)."""
    import numpy as np
    simulation.run(warm_up)
    rates, iterations = [], []
    for _ in range(blocks):
        start = time.perf_counter()
        trajectory = simulation.run(max(steps // blocks, 1))
        rates.append((len(trajectory.times) - 1) / (time.perf_counter() - start))
        iterations.extend(trajectory.iterations[1:])
    return max(rates), float(np.mean(iterations))


def case_dynamics(arg, warm_up=24, steps=96, exact_steps=12):
    """Subspace dynamics (SPEC 6) on a bar; arg = "<modes>" (the 10k-tet bar) or
    "<modes>:<size>" (a size of BAR_SIZES).

    Deformer: ``reduced.prepare_reduced_rs`` (default settings: cubature). Linear material
    (V = 1/2 s^T Lambda s, exact), gravity, h = 1/24 s, mass damping 0.5/s: released straight,
    the soft bar swings down through large rotations. Steps/s is timed after ``warm_up`` steps
    over ``steps`` (cubature), plain and with the inversion safety a simulation of a prepared
    body carries (``problems.simulation``: the RS volume barrier, the reconstruction barrier and
    the det F check of every tet, ``tets=``). On the 10k bar also ``exact_steps`` with no
    cubature (the same basis with every tet at weight 1, i.e. the exact all-tet reduced fit),
    and at 20 modes StVK with its energy cubature (``materials.prepare_potential`` defaults:
    200 poses, up to 200 tets). BLAS runs on one thread (set before numpy loads): a step is
    many small products, which lose several-fold to thread hand-offs when the cores are
    shared (the 12k bar under load: 2.9 against 44 steps/s).
    """
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    import numpy as np
    from solver import dynamics, fem, inversion, materials, reduced, rs
    num_modes, _, size = arg.partition(":")
    num_modes, size = int(num_modes), size or "10k"
    X, T, pinned, masses, body, recon = _dynamics_body(num_modes, size=size)
    modal_rs = rs.linear_rs(rs.rs_operator(X, T), body.vectors)
    start = time.perf_counter()
    deformer, info = reduced.prepare_reduced_rs(X, T, masses, body.vectors, body.eigenvalues,
                                                recon, modal_rs=modal_rs)
    prepare = time.perf_counter() - start
    volumes = fem.tet_volumes(X, T)
    mu, lam = fem.lame_parameters(1e6, 0.45)
    linear = materials.ReducedPotential.exact(materials.Linear(mu, lam), modal_rs, volumes)

    def simulate(deformer_, potential, count, tets=None):
        sim = dynamics.Simulation(deformer_, X, masses, potential, 1.0 / 24.0,
                                  gravity=(0.0, 0.0, -9.81), mass_damping=0.5, tets=tets)
        return _steps_per_second(sim, warm_up, count)

    rate, iterations = simulate(deformer, linear, steps)
    row = dict(modes=num_modes, size=size, tets=len(T), basis_size=deformer.basis_size,
               cubature_tets=len(deformer.cubature_tets), prepare_seconds=prepare,
               steps_per_second=rate, iterations=iterations)
    # as ``problems.simulation`` makes it: the barrier evaluates q with the simulation's own
    # deformer (``dynamics.step_deformer``; an older solver has none and shares nothing)
    stepping = getattr(dynamics, "step_deformer", lambda given: given)(deformer)
    safe = inversion.with_reconstruction_barrier(
        inversion.with_barrier(linear, modal_rs, volumes), stepping, X, T)
    row["safe_steps_per_second"], row["safe_iterations"] = simulate(stepping, safe, steps, T)
    if size != "10k":                  # the all-tet and StVK rows are the 10k bar's
        row["peak_rss_mb"] = peak_rss_mb()
        return row
    if num_modes == 20:
        stvk = _energy_cubature_row(row, "", materials.StVK(mu, lam), modal_rs, volumes,
                                    body.eigenvalues)
        _energy_cubature_row(row, "fung_", materials.make_material("FUNG", mu, lam), modal_rs,
                             volumes, body.eigenvalues)
        row["stvk_steps_per_second"], row["stvk_iterations"] = simulate(deformer, stvk, steps)
    start = time.perf_counter()
    everything = reduced.ReducedRS.build(X, T, modal_rs, deformer.basis, recon,
                                         np.arange(len(T)), np.ones(len(T)))
    row["exact_build_seconds"] = time.perf_counter() - start
    row["exact_steps_per_second"], row["exact_iterations"] = simulate(everything, linear,
                                                                      exact_steps)
    row["speedup"] = row["steps_per_second"] / row["exact_steps_per_second"]
    row["peak_rss_mb"] = peak_rss_mb()
    return row


def case_dynamics_reference(arg, steps=4):
    """Full-space reference step (tests' FullSpaceCorotational: corotational FEM, implicit
    Euler, Newton with sparse LU) on the same bar, gravity, h = 1/24: seconds per step."""
    from tests.solver.test_dynamics import FullSpaceCorotational
    from solver import fem
    X, T, pinned, masses, _, _ = _dynamics_body(1)
    mu, lam = fem.lame_parameters(1e6, 0.45)
    reference = FullSpaceCorotational(X, T, masses, mu, lam, 1.0 / 24.0, (0.0, 0.0, -9.81),
                                      pinned, mass_damping=0.5)
    start = time.perf_counter()
    iterations = [reference.step() for _ in range(steps)]
    seconds = (time.perf_counter() - start) / steps
    return dict(tets=len(T), nodes=len(X), steps=steps, seconds_per_step=seconds,
                steps_per_second=1.0 / seconds, iterations=sum(iterations) / steps,
                peak_rss_mb=peak_rss_mb())


def dynamics_table(rows, reference):
    """Markdown: steps/s per mode count, with the full-space reference step below."""
    text = table(
        "Subspace dynamics (pinned 4:1:1 bar, E = 1e6 Pa, gravity, h = 1/24, linear material; "
        "target >= 1,000 steps/s at 20 modes with cubature, the 98k bar within 25 % of the "
        "12k; safe: RS volume and reconstruction barriers and the det F check, as Simulate)",
        rows,
        [("modes", ("modes", "{}")), ("tets", ("tets", "{:,}")), ("rB", ("basis_size", "{}")),
         ("cubature tets", ("cubature_tets", "{}")), ("prepare s", ("prepare_seconds", "{:.1f}")),
         ("steps/s cubature", ("steps_per_second", "{:.0f}")),
         ("Newton it/step", ("iterations", "{:.2f}")),
         ("steps/s safe", ("safe_steps_per_second", "{:.0f}")),
         ("steps/s all tets", ("exact_steps_per_second", "{:.1f}")),
         ("Newton it/step (all)", ("exact_iterations", "{:.2f}")),
         ("speed-up", ("speedup", "{:.0f}x")), ("peak RSS MB", ("peak_rss_mb", "{:.0f}"))])
    extra = [row for row in rows if "stvk_steps_per_second" in row]
    if extra:
        text += "\n" + table(
            "Subspace dynamics with StVK (20 modes, energy cubature trained on 200 poses)", extra,
            [("modes", ("modes", "{}")), ("energy cubature tets", ("energy_cubature_tets", "{}")),
             ("training s", ("energy_cubature_seconds", "{:.1f}")),
             ("held-out force error mean / max", ("energy_cubature_force_error_mean", "{:.4f}")),
             ("", ("energy_cubature_force_error_max", "{:.4f}")),
             ("Fung training s", ("fung_energy_cubature_seconds", "{:.1f}")),
             ("Fung held-out error mean / max", ("fung_energy_cubature_force_error_mean",
                                                 "{:.4f}")),
             ("", ("fung_energy_cubature_force_error_max", "{:.4f}")),
             ("steps/s", ("stvk_steps_per_second", "{:.0f}")),
             ("Newton it/step", ("stvk_iterations", "{:.2f}"))])
    return text + "\n" + table(
        "Full-space reference step (corotational FEM, same bar, Newton + sparse LU)", [reference],
        [("tets", ("tets", "{:,}")), ("nodes", ("nodes", "{:,}")),
         ("s/step", ("seconds_per_step", "{:.2f}")), ("Newton it/step", ("iterations", "{:.1f}")),
         ("peak RSS MB", ("peak_rss_mb", "{:.0f}"))])


def _energy_cubature_row(row, prefix, material, modal_rs, volumes, eigenvalues, held_out=40):
    """Train ``material``'s energy cubature as Prepare does (``materials.prepare_potential``
    defaults) and add its seconds, tets, training residual and force error on ``held_out``
    poses it was not trained on (drawn alike, another seed; relative to the exact all-tet
    force: mean and max) to ``row`` under ``prefix``. Returns the potential."""
    import numpy as np
    from solver import cubature, materials
    start = time.perf_counter()
    potential, fit = materials.prepare_potential(material, modal_rs, volumes, eigenvalues)
    row[prefix + "energy_cubature_seconds"] = time.perf_counter() - start
    row[prefix + "energy_cubature_tets"] = len(fit["tets"])
    row[prefix + "energy_cubature_residual"] = float(fit["relative_residual"])
    exact = materials.ReducedPotential.exact(material, modal_rs, volumes)
    poses = cubature.training_poses(modal_rs.shape[2], eigenvalues, held_out,
                                    np.random.default_rng(1), max_rotation=np.pi / 2,
                                    modal_rs=modal_rs)
    errors = [np.linalg.norm(potential.gradient(s) - want) / np.linalg.norm(want)
              for s, want in ((s, exact.gradient(s)) for s in poses)]
    row[prefix + "energy_cubature_force_error_mean"] = float(np.mean(errors))
    row[prefix + "energy_cubature_force_error_max"] = float(np.max(errors))
    return potential


def case_integrators(arg, fps=24, seconds=2.0):
    """Time integration on the 10k-tet bar of ``case_dynamics`` (arg = number of modes),
    undamped, no gravity, released from its first mode (tip 1 cm): energy kept after 2 s at
    24 fps and speed, for Newmark with automatic substeps (the default) and implicit Euler
    at one step per frame (the old default) and with the same substeps. Energy is the
    integrator's own kinetic + elastic (``Simulation.energy``); speed is timed over the
    following second (``_steps_per_second``: fastest of 3 blocks)."""
    import numpy as np
    from solver import dynamics, fem, materials, reduced, rs
    num_modes = int(arg)
    X, T, pinned, masses, body, recon = _dynamics_body(num_modes)
    modal_rs = rs.linear_rs(rs.rs_operator(X, T), body.vectors)
    deformer, _ = reduced.prepare_reduced_rs(X, T, masses, body.vectors, body.eigenvalues,
                                             recon, modal_rs=modal_rs)
    mu, lam = fem.lame_parameters(1e6, 0.45)
    linear = materials.ReducedPotential.exact(materials.Linear(mu, lam), modal_rs,
                                              fem.tet_volumes(X, T))
    start = np.zeros(num_modes)
    start[0] = 0.01 / np.abs(body.vectors[:, 0]).max()
    rows = []
    for integrator, substeps in (("newmark", 0), ("implicit_euler", 1), ("implicit_euler", 0)):
        sim = dynamics.Simulation(deformer, X, masses, linear, 1.0 / fps, integrator=integrator,
                                  substeps=substeps)
        sim.set_state(start)
        before = sim.energy()["total"]
        sim.run(int(round(seconds * fps)))
        kept = sim.energy()["total"] / before
        rate, iterations = _steps_per_second(sim, 0, fps)   # one more second, timed
        rows.append(dict(integrator=integrator, substeps=sim.substeps,
                         f1_hz=float(sim.omega[0] / (2 * np.pi)),
                         f_max_hz=float(sim.omega[-1] / (2 * np.pi)), energy_kept=kept,
                         frames_per_second=rate, steps_per_second=rate * sim.substeps,
                         iterations=iterations / sim.substeps))
    return dict(modes=num_modes, tets=len(T), basis_size=deformer.basis_size, rows=rows,
                peak_rss_mb=peak_rss_mb())


def integrators_table(result):
    """Markdown: energy kept after 2 s and speed per integrator (``case_integrators``)."""
    if "error" in result:
        return table("Time integration", [result], [("modes", ("modes", "{}"))])
    return table(
        f"Time integration ({result['tets']:,}-tet pinned bar, {result['modes']} modes, "
        f"f1 = {result['rows'][0]['f1_hz']:.2f} Hz, undamped, released from mode 1, 2 s at "
        "24 fps)", result["rows"],
        [("integrator", ("integrator", "{}")), ("substeps", ("substeps", "{}")),
         ("energy kept after 2 s", ("energy_kept", "{:.4f}")),
         ("frames/s", ("frames_per_second", "{:.1f}")),
         ("steps/s", ("steps_per_second", "{:.0f}")),
         ("Newton it/step", ("iterations", "{:.2f}"))])


def case_shot(arg, frames=240, fps=24, num_modes=20):
    """A 240-frame shot of a ~20k-tet body (4:1:1 bar, 24,000 tets, E = 1e6 Pa, 20 modes) under
    gravity at 24 fps with the defaults (Newmark, automatic substeps, no damping): prepare time
    and frames per second of the whole shot. arg: cells across the bar (10 -> 24,000 tets)."""
    import numpy as np
    from solver import dynamics, fem, materials, meshgen, modes, reduced, rs
    n = int(arg)
    X, T = meshgen.box_tet_mesh((4.0, 1.0, 1.0), (4 * n, n, n))
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    masses = fem.lumped_masses(X, T, 1100.0)
    start = time.perf_counter()
    body = modes.linear_modes(fem.stiffness_matrix(X, T, 1e6, 0.45), masses, num_modes, pinned)
    modal_rs = rs.linear_rs(rs.rs_operator(X, T), body.vectors)
    deformer, _ = reduced.prepare_reduced_rs(X, T, masses, body.vectors, body.eigenvalues,
                                             rs.PoissonReconstruction(X, T, pinned),
                                             modal_rs=modal_rs)
    prepare = time.perf_counter() - start
    mu, lam = fem.lame_parameters(1e6, 0.45)
    linear = materials.ReducedPotential.exact(materials.Linear(mu, lam), modal_rs,
                                              fem.tet_volumes(X, T))
    sim = dynamics.Simulation(deformer, X, masses, linear, 1.0 / fps, gravity=(0.0, 0.0, -9.81))
    start = time.perf_counter()
    trajectory = sim.run(frames)
    seconds = time.perf_counter() - start
    return dict(tets=len(T), nodes=len(X), modes=num_modes, basis_size=deformer.basis_size,
                frames=frames, substeps=sim.substeps, prepare_seconds=prepare,
                simulate_seconds=seconds, frames_per_second=frames / seconds,
                iterations=float(np.mean(trajectory.iterations[1:])) / sim.substeps,
                peak_rss_mb=peak_rss_mb())


def shot_table(row):
    return table("A 240-frame shot at 24 fps (4:1:1 bar under gravity, defaults: Newmark, "
                 "automatic substeps)", [row],
                 [("tets", ("tets", "{:,}")), ("modes", ("modes", "{}")),
                  ("rB", ("basis_size", "{}")), ("substeps", ("substeps", "{}")),
                  ("prepare s", ("prepare_seconds", "{:.1f}")),
                  ("simulate s", ("simulate_seconds", "{:.1f}")),
                  ("frames/s", ("frames_per_second", "{:.1f}")),
                  ("Newton it/step", ("iterations", "{:.2f}")),
                  ("peak RSS MB", ("peak_rss_mb", "{:.0f}"))])


def amplitude_kept(tip_z, fps, window=0.5):
    """RMS of a tip height trace (F,) about its mean over its last ``window`` seconds, in that
    window over the first one: what is left of the motion (its square ~ the energy left), the
    same measure for any solver and any mix of modes."""
    import numpy as np
    n = max(int(round(window * fps)), 2)
    centre = float(np.mean(tip_z[-n:]))
    return float(np.sqrt(np.mean((tip_z[-n:] - centre) ** 2)
                         / np.mean((tip_z[:n] - centre) ** 2)))


def case_ring(arg, fps=24, seconds=2.0, youngs=1e8):
    """Energy kept after 2 s, the scene Blender's Soft Body runs too (``run_softbody``): the
    pinned 4:1:1 bar released straight under gravity, no damping set, 24 fps. Ours: the 10k-tet
    bar at E = 1e8 Pa (so it rings at about 3 Hz, several periods in 2 s, like the Soft Body
    bar with its stiffest springs), 20 modes, defaults (Newmark, automatic substeps): the tip's
    RMS motion in the last half second over the first (``amplitude_kept``), and the
    integrator's own energy about the static sag, E(2 s) / E(0)."""
    import numpy as np
    from solver import dynamics, fem, materials, reduced, rs
    X, T, pinned, masses, body, recon = _dynamics_body(int(arg), youngs)
    modal_rs = rs.linear_rs(rs.rs_operator(X, T), body.vectors)
    deformer, _ = reduced.prepare_reduced_rs(X, T, masses, body.vectors, body.eigenvalues,
                                             recon, modal_rs=modal_rs)
    mu, lam = fem.lame_parameters(youngs, 0.45)
    linear = materials.ReducedPotential.exact(materials.Linear(mu, lam), modal_rs,
                                              fem.tet_volumes(X, T))

    def simulation():
        return dynamics.Simulation(deformer, X, masses, linear, 1.0 / fps,
                                   gravity=(0.0, 0.0, -9.81))

    rest = simulation()
    rest.static_equilibrium()
    floor = rest.energy()["total"]
    sim = simulation()
    before = sim.energy()["total"] - floor
    trajectory = sim.run(int(round(seconds * fps)))
    kept = (sim.energy()["total"] - floor) / before
    tip = int(np.argmax(X[:, 0] + 1e-3 * X[:, 2]))
    tip_z = trajectory.world_positions(X[tip:tip + 1], deformer.basis[3 * tip:3 * tip + 3])
    return dict(solver="RS Elastic (Newmark, automatic substeps)", tets=len(T),
                energy_kept=kept, amplitude_kept=amplitude_kept(tip_z[:, 0, 2], fps),
                f1_hz=float(sim.omega[0] / (2.0 * np.pi)))


def case_contact(arg, seconds=3.0):
    """Steps per second with substeps and contact: the soft cube of tests/solver/
    test_collisions.py (0.2 m, 384 tets, 8 modes, E = 2e4 Pa, 60 contact samples) dropped 1 m
    onto a floor quad, 3 s at 24 fps with ``arg`` substeps, against the same fall with no floor
    (so without contact). Steps are internal steps (frames x substeps)."""
    import numpy as np
    from solver import dynamics
    from tests.solver.test_collisions import FPS, GRAVITY, build_body, quad, simulate
    substeps = int(arg)
    body = build_body((0.2, 0.2, 0.2), (4, 4, 4), 2e4, offset=np.array([-0.1, -0.1, 1.0]))
    floor = quad([[-5, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0]], damping=0.5)
    _, beta = dynamics.rayleigh_from_damping_ratio(0.05, body["omega"][0], 1.0)
    frames = int(round(seconds * FPS))
    row = dict(substeps=substeps, tets=len(body["T"]), samples=len(body["idx"]))
    for name, colliders in (("contact", [floor]), ("no_contact", None)):
        trajectory, _, wall = simulate(body, colliders, frames, gravity=GRAVITY, free=True,
                                       stiffness_damping=beta, substeps=substeps)
        row[f"{name}_steps_per_second"] = frames * substeps / wall
        row[f"{name}_iterations"] = float(np.mean(trajectory.iterations[1:])) / substeps
    row["peak_rss_mb"] = peak_rss_mb()
    return row


def contact_table(rows):
    return table("Contact: a soft cube dropped 1 m onto a floor, 3 s at 24 fps (free body, 60 "
                 "contact samples), against the same fall without the floor", rows,
                 [("substeps", ("substeps", "{}")), ("tets", ("tets", "{}")),
                  ("steps/s with contact", ("contact_steps_per_second", "{:.0f}")),
                  ("Newton it/step", ("contact_iterations", "{:.2f}")),
                  ("steps/s no contact", ("no_contact_steps_per_second", "{:.0f}")),
                  ("Newton it/step (no contact)", ("no_contact_iterations", "{:.2f}"))])


CASES["contact"] = case_contact
CASES["shot"] = case_shot
CASES["ring"] = case_ring
CASES["integrators"] = case_integrators
CASES["dynamics"] = case_dynamics
CASES["dynamics_reference"] = case_dynamics_reference

def case_pins(surface, meshes=5, edge=0.02):
    """f1 / f_EB of the clamped 1 x 0.1 x 0.1 m cantilever (E 1e6, nu 0.3, rho 1000) on fresh
    fTetWild meshes (edge 0.02 m), end face pinned by the old rule (tet nodes carrying weight
    for the pinned render vertices) and the new one (``embed.pin_surface``).
    surface: "box" (8 vertices, 12 triangles) or "fine" (40 x 4 x 4 cells)."""
    import igl
    import numpy as np
    from solver import embed, fem, meshgen, modes, tetmesh
    cells = {"box": (1, 1, 1), "fine": (40, 4, 4)}[surface]
    Xs, Ts = meshgen.box_tet_mesh((1.0, 0.1, 0.1), cells)
    used, F = np.unique(igl.boundary_facets(Ts)[0], return_inverse=True)
    V, F = Xs[used], F.reshape(-1, 3)
    weights = (V[:, 0] < 1e-9).astype(np.float64)
    f_eb = 1.8751041 ** 2 * np.sqrt(1e6 * 0.1 ** 4 / 12.0 / (1000.0 * 0.01)) / (2.0 * np.pi)
    ratios = dict(old=[], new=[])
    start = time.perf_counter()
    for _ in range(meshes):
        X, T = tetmesh.tetrahedralize(V, F, edge_length_fac=edge / np.linalg.norm([1, .1, .1]))
        Phi = embed.embed_points(X, T, V)
        K, m = fem.stiffness_matrix(X, T, 1e6, 0.3), fem.lumped_masses(X, T, 1000.0)
        pins = dict(old=embed.pinned_nodes_from_vertices(Phi, weights >= 0.5),
                    new=embed.pin_surface(X, T, Phi, V, F, weights).nodes)
        for rule, pinned in pins.items():
            f1 = modes.linear_modes(K, m, 1, pinned, rest_positions=X).frequencies_hz[0]
            ratios[rule].append(float(f1 / f_eb))
    return dict(surface=surface, meshes=meshes, seconds=time.perf_counter() - start,
                old_min=min(ratios["old"]), old_max=max(ratios["old"]),
                new_min=min(ratios["new"]), new_max=max(ratios["new"]),
                old_spread=100.0 * (max(ratios["old"]) / min(ratios["old"]) - 1.0),
                new_spread=100.0 * (max(ratios["new"]) / min(ratios["new"]) - 1.0),
                old=ratios["old"], new=ratios["new"])


def pins_table(rows):
    return table("Clamped cantilever f1 / f_EB over fresh fTetWild meshes: old pin rule (nodes "
                 "of the pinned vertices) vs new (pinned faces clamp)", rows,
                 [("surface", ("surface", "{}")), ("meshes", ("meshes", "{}")),
                  ("old min", ("old_min", "{:.3f}")), ("old max", ("old_max", "{:.3f}")),
                  ("old spread %", ("old_spread", "{:.2f}")),
                  ("new min", ("new_min", "{:.3f}")), ("new max", ("new_max", "{:.3f}")),
                  ("new spread %", ("new_spread", "{:.2f}")), ("s", ("seconds", "{:.1f}"))])


CASES["pins"] = case_pins


def run_softbody(frames=120, cuts=20, stiff=False):
    """Blender's own Soft Body on a bar of about the 10k-tet bar's node count (bench/softbody.py,
    in its own process since it imports bpy). stiff: the ringing variant, with the tip's motion
    kept after 2 s at 24 fps (``amplitude_kept``), as in ``case_ring``."""
    import numpy as np
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "softbody.py"), str(frames),
                          str(cuts), str(int(stiff))], capture_output=True, text=True, cwd=ROOT)
    if out.returncode != 0:
        return dict(case="softbody", arg=str(cuts), error=(out.stderr.strip().splitlines() or ["?"])[-1])
    row = json.loads(out.stdout.strip().splitlines()[-1])
    tip_z = np.array(row.pop("tip_z"))[:49]                     # frames 1..49: 2 s at 24 fps
    row["amplitude_kept"] = amplitude_kept(tip_z, 24)
    return row


def softbody_table(softbody, dynamics):
    """Markdown: Blender Soft Body per frame against an RS step at 20 modes with cubature."""
    rs_row = next((r for r in dynamics if "error" not in r and str(r.get("modes")) == "20"), None)
    lines = ["## Blender Soft Body against RS dynamics (same frames)", "",
             "| solver | points | ms per frame |", "|---|---|---|"]
    if "error" in softbody:
        lines.append(f"| Soft Body | error: {softbody['error']} | |")
    else:
        lines.append(f"| Blender Soft Body (surface springs) | {softbody['vertices']:,} vertices "
                     f"| {softbody['ms_per_frame']:.2f} |")
    if rs_row is not None and "steps_per_second" in rs_row:
        lines.append(f"| RS dynamics, 20 modes, cubature | {rs_row.get('tets', 0):,} tets "
                     f"| {1000.0 / rs_row['steps_per_second']:.2f} |")
    return "\n".join(lines) + "\n"


def ring_table(ring, softbody):
    """Markdown: what is left of the motion after 2 s, ours against Soft Body (same scene)."""
    lines = ["## Motion kept after 2 s (pinned 4:1:1 bar released under gravity, no damping set, "
             "24 fps)", "", "| solver | tip RMS motion kept (last 0.5 s / first 0.5 s) | energy kept |", "|---|---|---|"]
    if "error" not in ring:
        lines.append(f"| {ring['solver']}, {ring['tets']:,} tets | {ring['amplitude_kept']:.3f} "
                     f"| {ring['energy_kept']:.3f} |")
    if "error" not in softbody:
        lines.append(f"| Blender Soft Body ({softbody['vertices']:,} vertices, goal-pinned end, "
                     "no friction, stiffest springs) | "
                     f"{softbody['amplitude_kept']:.3f} | ~{softbody['amplitude_kept'] ** 2:.3f} "
                     "(RMS kept squared; Soft Body reports no energy) |")
    return "\n".join(lines) + "\n"


def case_rig(arg, frames=240, num_modes=20):
    """A 240-frame shot of a ~30k-tet bar skinned to 3 bones (issue 13): the bones turn and
    stop; the flesh past the first bone is free. Prepare (modes, default reduced RS, node
    weights, the rig load's moments) and the simulation loop are timed apart. The body and the
    simulation are built as a rigged body's Simulate builds them (``solver.preparation``,
    ``solver.problems``)."""
    import numpy as np
    from scipy.spatial.transform import Rotation
    from solver import meshgen, preparation, problems, rig
    X, T = meshgen.box_tet_mesh((3.0, 0.5, 0.5), (54, 10, 10))             # 32,400 tets
    h = 1.0 / 24.0
    start = time.perf_counter()
    pinned = np.flatnonzero(X[:, 0] < 1.0 + 1e-9)              # bone 1's segment follows
    body = preparation.prepare_body(X, T, X, 5e5, 0.45, 1000.0, num_modes, pinned=pinned)
    masses = body.lumped_masses(1000.0)
    centres = np.array([0.5, 1.5, 2.5])
    weights = np.maximum(0.0, 1.0 - np.abs(X[:, :1] - centres[None]))      # blended bones
    weights /= weights.sum(axis=1)[:, None]
    times = np.arange(frames) * h
    transforms = np.zeros((frames, 3, 3, 4))
    for b, (joint, degrees) in enumerate(((0.0, 0.0), (1.0, 40.0), (2.0, 60.0))):
        fraction = np.clip((np.arange(frames) - 10) / 12.0, 0.0, 1.0)      # turn, then stop
        R = Rotation.from_rotvec(np.radians(degrees) * fraction[:, None] * [0, 0, 1]).as_matrix()
        pivot = np.array([joint, 0.25, 0.25])
        transforms[:, b, :, :3] = R
        transforms[:, b, :, 3] = pivot - R @ pivot
    load = rig.RigLoad(rig.RigMotion(times, transforms), weights, masses, body.deformer.basis, X,
                       gravity=(0.0, 0.0, -9.81))
    simulation = problems.simulation(
        body, problems.linear_potential(body, 5e5, 0.45),
        problems.SimulationSettings(h=h, density=1000.0, substeps=1), external_force=load.force)
    prepare_seconds = time.perf_counter() - start
    start = time.perf_counter()
    simulation.run(frames - 1)
    seconds = time.perf_counter() - start
    deformer = body.deformer
    return dict(tets=len(T), nodes=len(X), modes=num_modes, frames=frames, bones=3,
                basis_size=deformer.basis_size, load_pairs=len(load.pairs),
                substeps=simulation.substeps, prepare_seconds=prepare_seconds,
                seconds=seconds, frames_per_second=(frames - 1) / seconds,
                peak_rss_mb=peak_rss_mb())


def rig_table(row):
    lines = ["## A rig shot: 240 frames of a 3-bone skinned bar (issue 13; target < 10 s)", "",
             "| tets | modes | rB | bone pairs | substeps | prepare s | shot s | frames/s "
             "| peak RSS MB |", "|" + "---|" * 9]
    if "error" in row:
        lines.append(f"| error: {row['error']} |")
    else:
        lines.append(f"| {row['tets']:,} | {row['modes']} | {row['basis_size']} "
                     f"| {row['load_pairs']} | {row['substeps']} | {row['prepare_seconds']:.1f} "
                     f"| {row['seconds']:.1f} | {row['frames_per_second']:.0f} "
                     f"| {row['peak_rss_mb']:.0f} |")
    return "\n".join(lines) + "\n"


CASES["rig"] = case_rig


def case_take(arg, stiffer=1.5, tip=0.8):
    """Take from Animation, Fit Material and Continue at the solver level, as the operators call
    it (``solver.take``); arg "MODES:FRAMES" (the bench row: 20 modes, 100 frames).

    Body: the 10k-tet pinned 4:1:1 bar (E = 1e6 Pa, nu = 0.45, 1100 kg/m^3), default reduced RS
    (setup, timed apart). Take: FRAMES frames of a free vibration of its modes with a material
    ``stiffer`` times as stiff (Rayleigh 0.05, 0.002), from a first-mode bend whose tip moves
    ``tip`` m (20 % of the length: rotations the linear regime would miss), as surface positions.
    Timed: the take to modal coordinates (``take_to_modal``); the fit of all its frames; the
    continuation over FRAMES more frames (``continue_motion`` and the surface positions). Errors
    against the truth over the continued frames, for the fitted material and for the prepared
    (uniform) one continued the same way, over the diagonal.
    """
    import numpy as np
    from solver import meshgen, preparation, spacetime, take
    num_modes, _, frames = arg.partition(":")
    num_modes, frames = int(num_modes), int(frames or 100)
    n, h = BAR_SIZES["10k"], 1.0 / 24.0
    X, T = meshgen.box_tet_mesh((4.0, 1.0, 1.0), (4 * n, n, n))
    start = time.perf_counter()
    body = preparation.prepare_body(X, T, X, 1e6, 0.45, 1100.0, num_modes,
                                    pinned=np.flatnonzero(X[:, 0] < 1e-9))
    setup = time.perf_counter() - start
    eigenvalues = stiffer * body.linear_modes.eigenvalues
    damping = spacetime.rayleigh_damping(eigenvalues, 0.05, 0.002)
    z0 = np.zeros(num_modes)
    z0[0] = 1.0
    z0 *= tip / np.abs(body.surface_positions(X, z0) - X).max()     # linear scale of the bend
    truth = body.surface_positions(X, spacetime.simulate_modal(
        eigenvalues, damping, z0, z0, 2 * frames, h, "average"))
    keyed, after = np.arange(1, frames + 1), truth[frames:]

    start = time.perf_counter()
    inputs, residuals = take.take_to_modal(body, X, truth[:frames])
    take_seconds = time.perf_counter() - start
    start = time.perf_counter()
    fitted = take.fit_material(body, X, keyed, truth[:frames], inputs, h, 0.05, 0.002)
    fit_seconds = time.perf_counter() - start
    start = time.perf_counter()
    continued = body.surface_positions(X, take.continue_motion(fitted, frames))
    continue_seconds = time.perf_counter() - start
    uniform = take.fit_material(body, X, keyed, truth[:frames], inputs, h, 0.05, 0.002,
                                optimise=False)
    uniform_continued = body.surface_positions(X, take.continue_motion(uniform, frames))
    diagonal = float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))

    def error(positions):
        return float(np.sqrt(np.mean(np.sum((positions - after) ** 2, axis=2)))) / diagonal

    return dict(modes=num_modes, fitted_modes=len(fitted.eigenvalues), frames=frames,
                tets=len(T), vertices=len(X), setup_seconds=setup, take_seconds=take_seconds,
                take_residual=float(residuals.max()) / diagonal, fit_seconds=fit_seconds,
                fit_residual=fitted.residual / diagonal, converged=fitted.converged,
                continue_seconds=continue_seconds, continued_error=error(continued),
                uniform_error=error(uniform_continued), peak_rss_mb=peak_rss_mb())


def take_table(row):
    lines = ["## Take, Fit Material and Continue (10k-tet pinned bar, reduced RS, solver level; "
             "a take of a 1.5x stiffer material, tip bent 20 % of the length)", "",
             "| modes (fitted) | frames | take s | fit s | converged | continue s (as many frames) "
             "| take residual / diag | fit residual / diag | continued error / diag: fitted, "
             "uniform | setup s |", "|" + "---|" * 10]
    if "error" in row:
        lines.append(f"| error: {row['error']} |")
    else:
        lines.append(f"| {row['modes']} ({row['fitted_modes']}) | {row['frames']} "
                     f"| {row['take_seconds']:.2f} | {row['fit_seconds']:.1f} "
                     f"| {row['converged']} | {row['continue_seconds']:.3f} "
                     f"| {row['take_residual']:.1e} | {row['fit_residual']:.1e} "
                     f"| {row['continued_error']:.1e}, {row['uniform_error']:.1e} "
                     f"| {row['setup_seconds']:.1f} |")
    return "\n".join(lines) + "\n"


CASES["take"] = case_take


def run_mesh_cache_shot(frames=1000, cuts=90):
    """A 1,000-frame simulate-and-bake of a ~50k-vertex bar to a Mesh Cache, in Blender with the
    extension installed from its zip (bench/mesh_cache_shot.py, its own process)."""
    zips = sorted((ROOT / "dist").glob("rs_elastic-*-linux_x64.zip"))
    if not zips:
        return dict(case="mesh_cache", arg=str(frames), error="no extension zip: run make build")
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "mesh_cache_shot.py"),
                          str(zips[-1]), str(frames), str(cuts)],
                         capture_output=True, text=True, cwd=ROOT)
    if out.returncode != 0:
        return dict(case="mesh_cache", arg=str(frames),
                    error=(out.stderr.strip().splitlines() or ["?"])[-1])
    return json.loads(out.stdout.strip().splitlines()[-1])


def mesh_cache_table(row):
    lines = ["## A long shot baked to a Mesh Cache (pinned bar, Blender, extension from its zip)",
             "", "| vertices | frames | tets | Prepare s | simulate and bake s | .blend growth "
             "| .pc2 MB | shape keys would hold MB | playback error / diagonal |",
             "|---|---|---|---|---|---|---|---|---|"]
    if "error" in row:
        lines.append(f"| error: {row['error']} |")
    else:
        lines.append(f"| {row['vertices']:,} | {row['frames']:,} | {row['tets']:,} "
                     f"| {row['prepare_seconds']:.1f} | {row['simulate_and_bake_seconds']:.1f} "
                     f"| {row['blend_growth_bytes']:,} B | {row['pc2_bytes'] / 2 ** 20:.0f} "
                     f"| {row['shape_key_bytes'] / 2 ** 20:.0f} | {row['playback_error']:.1e} |")
    return "\n".join(lines) + "\n"


def run_farm_shot():
    """The three-body shot on a Flamenco manager and one worker against the same bakes one
    after another on the command line (bench/farm_shot.py, its own process)."""
    zips = sorted((ROOT / "dist").glob("rs_elastic-*-linux_x64.zip"))
    if not zips:
        return dict(case="farm", arg="3", error="no extension zip: run make build")
    source = os.environ.get("FLAMENCO_SRC", str(ROOT.parent / "shared" / "flamenco"))
    binaries = os.environ.get("FLAMENCO_BIN", str(ROOT / "build" / "flamenco"))
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "farm_shot.py"), str(zips[-1]),
                          os.path.abspath(source), os.path.abspath(binaries)],
                         capture_output=True, text=True, cwd=ROOT)
    if out.returncode != 0:
        return dict(case="farm", arg="3", error=(out.stderr.strip().splitlines() or ["?"])[-1])
    return json.loads(out.stdout.strip().splitlines()[-1])


def farm_table(row):
    lines = ["## A shot on the farm (three bodies, one Flamenco worker, Blender = bpy module)", "",
             "| bodies | frames | pickup s | farm s | command line s | overhead s | tasks s |",
             "|---|---|---|---|---|---|---|"]
    if "error" in row:
        lines.append(f"| error: {row['error']} |")
    else:
        tasks = ", ".join(f"{name} {s:.1f}" for name, s in row["task_seconds"].items())
        lines.append(f"| {row['bodies']} | {row['frames']} | {row['pickup_seconds']:.1f} "
                     f"| {row['farm_seconds']:.1f} | {row['command_line_seconds']:.1f} "
                     f"| {row['overhead_seconds']:.1f} | {tasks} |")
    lines += ["", "pickup: submission to the first task (an idle worker asks every 20 s); farm: "
              "first task to the job's end (three bakes and the collect task); command line: "
              "the same three bakes one after another."]
    return "\n".join(lines) + "\n"


def run_child(case, arg, env=None):
    out = subprocess.run([sys.executable, __file__, "--child", case, arg],
                         capture_output=True, text=True, cwd=ROOT, env=env)
    if out.returncode != 0:
        return dict(case=case, arg=arg, error=(out.stderr.strip().splitlines() or ["?"])[-1])
    return json.loads(out.stdout.strip().splitlines()[-1])


def table(title, rows, columns):
    lines = [f"## {title}", "", "| " + " | ".join(c for c, _ in columns) + " |",
             "|" + "---|" * len(columns)]
    for row in rows:
        if "error" in row:
            lines.append(f"| {row['arg']} | error: {row['error']} |")
            continue
        lines.append("| " + " | ".join(fmt.format(row[key]) if key in row else "-"
                                       for _, (key, fmt) in columns) + " |")
    return "\n".join(lines) + "\n"


# Rows measured with the baseline's solver and the current one back to back (--baseline REV):
# (case, arg, the figures compared; a trailing * matches every index of a list of rows).
COMPARED = [
    ("cubature", "10k:20:6", ["cubature_seconds", "prepare_seconds", "fit_residual",
                              "max_error", "mean_error", "seeds_mean_of_max",
                              "seeds_worst_max", "seeds_mean_error"]),
    ("cubature", "10k:40", ["cubature_seconds", "prepare_seconds", "fit_residual", "max_error",
                            "mean_error"]),
    ("dynamics", "20", ["steps_per_second", "safe_steps_per_second", "stvk_steps_per_second",
                        "prepare_seconds", "*energy_cubature*"]),
    ("spacetime", "20:200,400,800", ["rows[*].seconds", "rows[*].gn_iterations",
                                     "rows[*].converged", "rows[*].residual"]),
    ("take", "20:100", ["take_seconds", "fit_seconds", "continue_seconds", "continued_error"]),
    ("prepare", "spot", ["*seconds*"]),
    ("prepare", "cow", ["*seconds*"]),
    ("prepare", "knight256k", ["*seconds*"]),
]


def run_comparison(revision, quick=False):
    """[{case, arg, keys, baseline: row, current: row}] of COMPARED, each pair back to back."""
    import baseline
    pairs = []
    with baseline.exported_solver(ROOT, revision) as old_root:
        old_env = baseline.child_environment(old_root, ROOT / ".deps")
        new_env = baseline.child_environment(ROOT, ROOT / ".deps")
        for case, arg, keys in COMPARED[:1] if quick else COMPARED:
            pairs.append(dict(case=case, arg=arg, keys=keys,
                              baseline=run_child(case, arg, env=old_env),
                              current=run_child(case, arg, env=new_env)))
    return pairs


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--output", default="bench_output")
    parser.add_argument("--child", nargs=2)
    parser.add_argument("--quick", action="store_true", help="smallest sizes only")
    parser.add_argument("--farm", action="store_true",
                        help="only the farm row (needs `make build flamenco`)")
    parser.add_argument("--baseline", metavar="REV",
                        help="also measure COMPARED's rows with the solver of git revision REV")
    parser.add_argument("--compare-only", action="store_true",
                        help="only the before/after rows of --baseline")
    args = parser.parse_args()
    if args.child:
        print(json.dumps(CASES[args.child[0]](args.child[1])))
        return
    if args.farm:
        row = run_farm_shot()
        print(json.dumps(row))
        print(farm_table(row))
        return
    if args.compare_only:
        if not args.baseline:
            parser.error("--compare-only needs --baseline REV")
        import baseline
        pairs = run_comparison(args.baseline, args.quick)
        output = pathlib.Path(args.output)
        output.mkdir(parents=True, exist_ok=True)
        (output / "comparison.json").write_text(json.dumps(pairs, indent=2))
        text = baseline.comparison_table(pairs, args.baseline)
        (output / "comparison.md").write_text(text)
        print(text)
        return

    meshes = sorted(p.name for p in MESHES.iterdir())
    sizes = ["10k"] if args.quick else list(BAR_SIZES)
    results = dict(machine=dict(python=platform.python_version(), cpu=platform.processor(),
                                cores=__import__("os").cpu_count()),
                   tetrahedralize=[run_child("tetrahedralize", m)
                                   for m in meshes + ["knight256k"]],
                   modes=[run_child("modes", s + kind) for kind in ("", ":nd", ":chol")
                          for s in sizes],
                   modes_agreement=[run_child("modes_agreement", s) for s in sizes[:2]],
                   rs_full=[run_child("rs_full", s) for s in sizes])
    output = pathlib.Path(args.output)
    output.mkdir(parents=True, exist_ok=True)
    (output / "results.json").write_text(json.dumps(results, indent=2))
    text = "# RS Elastic benchmarks\n\n" + tetrahedralize_table(results["tetrahedralize"])
    text += "\n" + table(
        "Assembly and 20 linear modes (pinned 4:1:1 bar; shift-invert Lanczos on SuperLU ordered "
        "by its minimum degree (first) or by nested dissection (second), or on the supernodal "
        "Cholesky over that nested dissection (now the default); target at 100k: < 10 s, < 1 GB)",
        results["modes"],
        [("size", ("size", "{}")), ("factorisation", ("factorisation", "{}")), ("nodes", ("nodes", "{:,}")),
         ("tets", ("tets", "{:,}")), ("assembly s", ("assembly_seconds", "{:.2f}")),
         ("modes s", ("modes_seconds", "{:.2f}")),
         ("modes peak RSS MB", ("modes_peak_rss_mb", "{:.0f}")),
         ("process peak RSS MB", ("peak_rss_mb", "{:.0f}")),
         ("RSS before MB", ("rss_before_mb", "{:.0f}"))]
    ) + "\n" + table(
        "Old and new modes agree (targets: eigenvalues within 1e-6 relative, principal angles "
        "< 1e-4 rad)", results["modes_agreement"],
        [("size", ("size", "{}")), ("tets", ("tets", "{:,}")),
         ("max eigenvalue difference", ("max_relative_eigenvalue_difference", "{:.1e}")),
         ("max principal angle rad", ("max_principal_angle", "{:.1e}"))]
    ) + "\n" + table(
        "Full RS reconstruction y -> u (pinned 4:1:1 bar, first mode, tip 8x thickness)",
        results["rs_full"],
        [("size", ("size", "{}")), ("nodes", ("nodes", "{:,}")), ("tets", ("tets", "{:,}")),
         ("factor s", ("factor_seconds", "{:.3f}")),
         ("reconstruct s", ("reconstruct_seconds", "{:.4f}")),
         ("volume ratio", ("volume_ratio", "{:.3f}")),
         ("peak RSS MB", ("peak_rss_mb", "{:.0f}")), ("RSS before MB", ("rss_before_mb", "{:.0f}"))])
    results["reduced_rs"] = [run_child("reduced_rs", s) for s in sizes]
    text += "\n" + reduced_rs_table(results["reduced_rs"])
    results["cubature"] = [run_child("cubature", row) for row in CUBATURE_ROWS
                           if not args.quick or row.startswith("10k:")]
    (output / "results.json").write_text(json.dumps(results, indent=2))
    text += "\n" + cubature_table(results["cubature"])
    results["spacetime"] = spacetime_rows(args.quick)
    (output / "results.json").write_text(json.dumps(results, indent=2))
    text += "\n" + spacetime_table(results["spacetime"])
    results["live"] = run_child("live", "20")
    (output / "results.json").write_text(json.dumps(results, indent=2))
    text += "\n" + live_table(results["live"])
    results["dynamics"] = [run_child("dynamics", m)
                           for m in (("20",) if args.quick else DYNAMICS_MODES)]
    results["dynamics_reference"] = run_child("dynamics_reference", "10k")
    (output / "results.json").write_text(json.dumps(results, indent=2))
    text += "\n" + dynamics_table(results["dynamics"], results["dynamics_reference"])
    results["integrators"] = run_child("integrators", "20")
    (output / "results.json").write_text(json.dumps(results, indent=2))
    text += "\n" + integrators_table(results["integrators"])
    results["shot"] = run_child("shot", "10")
    results["ring"] = run_child("ring", "20")
    (output / "results.json").write_text(json.dumps(results, indent=2))
    text += "\n" + shot_table(results["shot"])
    results["contact"] = [run_child("contact", n) for n in ("1", "4")]
    (output / "results.json").write_text(json.dumps(results, indent=2))
    text += "\n" + contact_table(results["contact"])
    results["pins"] = [run_child("pins", surface) for surface in ("box", "fine")]
    (output / "results.json").write_text(json.dumps(results, indent=2))
    text += "\n" + pins_table(results["pins"])
    results["softbody"] = run_softbody()
    results["softbody_ring"] = run_softbody(frames=49, cuts=8, stiff=True)
    (output / "results.json").write_text(json.dumps(results, indent=2))
    text += "\n" + softbody_table(results["softbody"], results["dynamics"])
    text += "\n" + ring_table(results["ring"], results["softbody_ring"])
    results["rig"] = run_child("rig", "240")
    (output / "results.json").write_text(json.dumps(results, indent=2))
    text += "\n" + rig_table(results["rig"])
    results["take"] = run_child("take", "20:100")
    (output / "results.json").write_text(json.dumps(results, indent=2))
    text += "\n" + take_table(results["take"])
    results["prepare"] = [run_child("prepare", name) for name in PREPARE_MESHES]
    results["prepare_dense"] = results["prepare"][-1]                # knight256k
    (output / "results.json").write_text(json.dumps(results, indent=2))
    text += "\n" + prepare_table(results["prepare"])
    text += "\n" + prepare_dense_table(results["prepare_dense"])
    results["mesh_cache"] = run_mesh_cache_shot()
    (output / "results.json").write_text(json.dumps(results, indent=2))
    text += "\n" + mesh_cache_table(results["mesh_cache"])
    results["farm"] = run_farm_shot()
    (output / "results.json").write_text(json.dumps(results, indent=2))
    text += "\n" + farm_table(results["farm"])
    if args.baseline:
        import baseline
        results["comparison"] = run_comparison(args.baseline, args.quick)
        (output / "results.json").write_text(json.dumps(results, indent=2))
        text += "\n" + baseline.comparison_table(results["comparison"], args.baseline)
    (output / "results.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
