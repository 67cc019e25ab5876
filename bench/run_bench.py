"""`make bench`: speed and memory of the solver, written as JSON plus a readable table.

Each case runs in its own child process so its peak memory (max RSS) is its own. Times are wall
clock on this machine; compare ratios within one run only.

    python bench/run_bench.py --output bench_output [--quick]
"""
import argparse
import json
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


def read_surface(path):
    import igl
    if path.suffix == ".mesh":          # a MEDIT tet mesh: tetrahedralise its surface anew
        V, _, F = igl.readMESH(str(path))
        return V, F
    V, F = igl.read_triangle_mesh(str(path))[:2]
    return V, F


def case_tetrahedralize(name):
    import numpy as np
    from solver import tetmesh
    V, F = read_surface(MESHES / name)
    start = time.perf_counter()
    X, T = tetmesh.tetrahedralize(np.asarray(V, float), np.asarray(F, np.int64))
    seconds = time.perf_counter() - start
    return dict(mesh=name, surface_vertices=len(V), surface_faces=len(F), nodes=len(X),
                tets=len(T), seconds=seconds)


def case_modes(size):
    import numpy as np
    from solver import fem, meshgen, modes
    n = BAR_SIZES[size]
    X, T = meshgen.box_tet_mesh((4.0, 1.0, 1.0), (4 * n, n, n))
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    baseline = peak_rss_mb()
    start = time.perf_counter()
    K = fem.stiffness_matrix(X, T, 1e6, 0.45)
    m = fem.lumped_masses(X, T, 1100.0)
    assembly = time.perf_counter() - start
    start = time.perf_counter()
    result = modes.linear_modes(K, m, 20, pinned)
    mode_seconds = time.perf_counter() - start
    return dict(size=size, nodes=len(X), tets=len(T), assembly_seconds=assembly,
                modes_seconds=mode_seconds, num_modes=20,
                first_frequency_hz=float(result.frequencies_hz[0]),
                peak_rss_mb=peak_rss_mb(), rss_before_mb=baseline)


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
    W = modes.linear_modes(K, fem.lumped_masses(X, T, 1100.0), 1, pinned).vectors
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


CASES = {"tetrahedralize": case_tetrahedralize, "modes": case_modes, "rs_full": case_rs_full}


def run_child(case, arg):
    out = subprocess.run([sys.executable, __file__, "--child", case, arg],
                         capture_output=True, text=True, cwd=ROOT)
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
        lines.append("| " + " | ".join(fmt.format(row[key]) for key, fmt in
                                       ((k, f) for _, (k, f) in columns)) + " |")
    return "\n".join(lines) + "\n"


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--output", default="bench_output")
    parser.add_argument("--child", nargs=2)
    parser.add_argument("--quick", action="store_true", help="smallest sizes only")
    args = parser.parse_args()
    if args.child:
        print(json.dumps(CASES[args.child[0]](args.child[1])))
        return

    meshes = sorted(p.name for p in MESHES.iterdir())
    sizes = ["10k"] if args.quick else list(BAR_SIZES)
    results = dict(machine=dict(python=platform.python_version(), cpu=platform.processor(),
                                cores=__import__("os").cpu_count()),
                   tetrahedralize=[run_child("tetrahedralize", m) for m in meshes],
                   modes=[run_child("modes", s) for s in sizes],
                   rs_full=[run_child("rs_full", s) for s in sizes])
    output = pathlib.Path(args.output)
    output.mkdir(parents=True, exist_ok=True)
    (output / "results.json").write_text(json.dumps(results, indent=2))
    text = "# RS Elastic benchmarks\n\n" + table(
        "Tetrahedralisation (fTetWild, edge 0.05 of the diagonal, envelope 1e-3)",
        results["tetrahedralize"],
        [("mesh", ("mesh", "{}")), ("surface faces", ("surface_faces", "{:,}")),
         ("nodes", ("nodes", "{:,}")), ("tets", ("tets", "{:,}")), ("s", ("seconds", "{:.2f}"))]
    ) + "\n" + table(
        "Assembly and 20 linear modes (pinned 4:1:1 bar)", results["modes"],
        [("size", ("size", "{}")), ("nodes", ("nodes", "{:,}")), ("tets", ("tets", "{:,}")),
         ("assembly s", ("assembly_seconds", "{:.2f}")), ("modes s", ("modes_seconds", "{:.2f}")),
         ("peak RSS MB", ("peak_rss_mb", "{:.0f}")), ("RSS before MB", ("rss_before_mb", "{:.0f}"))]
    ) + "\n" + table(
        "Full RS reconstruction y -> u (pinned 4:1:1 bar, first mode, tip 8x thickness)",
        results["rs_full"],
        [("size", ("size", "{}")), ("nodes", ("nodes", "{:,}")), ("tets", ("tets", "{:,}")),
         ("factor s", ("factor_seconds", "{:.3f}")),
         ("reconstruct s", ("reconstruct_seconds", "{:.4f}")),
         ("volume ratio", ("volume_ratio", "{:.3f}")),
         ("peak RSS MB", ("peak_rss_mb", "{:.0f}")), ("RSS before MB", ("rss_before_mb", "{:.0f}"))])
    (output / "results.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
