"""The scene zoo (issue 26): every operator and the command line over generated scenes.

The cases are not listed: tests/blender/zoo.py builds them from independent scene features
(every mesh modifier type of `bpy.types.Modifier`'s enum, transforms, modes, linkage, bake
targets, frame ranges, bakers), drawn so that every pair of feature values meets in some case
(a seeded covering array). `make test` runs its first cases; `make test-zoo`
(RS_ELASTIC_ZOO=full) runs all of them. Each case runs in its own Blender process, so a hang is
cut at the case's time bound and a crash fails only its case; the child reports every step, and
this test fails on any broken invariant (see zoo.py), naming the case's scene in its id, e.g.
`NODES_deform-afterprep-negscale-edit-single-cache-3f-simulate` (a deforming Geometry Nodes
modifier added after Prepare, a mirroring scale, Edit Mode, a Mesh Cache bake of 3 frames).

RS_ELASTIC_ZOO_REPORT=FILE writes the failures grouped by cause (a Markdown table) at the end.
"""
import collections
import dataclasses
import os
import signal
import subprocess
import sys
import time

import pytest

import zoo
from conftest import USER_DIR

FULL = os.environ.get("RS_ELASTIC_ZOO") == "full"
TIMEOUT = float(os.environ.get("RS_ELASTIC_ZOO_TIMEOUT", "120"))
REPORT = os.environ.get("RS_ELASTIC_ZOO_REPORT")
# The older Blenders of `make test-matrix` run a smaller sample (RS_ELASTIC_ZOO_SAMPLE).
CASES = zoo.cases(full=FULL, sample=int(os.environ.get("RS_ELASTIC_ZOO_SAMPLE",
                                                        zoo.SAMPLE_SIZE)))
RESULTS = []                        # (case id, [Violation], seconds) of the cases run

CHILD = """
import sys
sys.path.insert(0, {tools!r})
sys.path.insert(0, {tests!r})
import zoo
zoo.run({spec!r})
"""


def run_case(case, folder):
    """Run the case in a new Blender process; every broken invariant it saw, with a case
    that outlives its time bound, or a Blender that dies, as broken invariants too."""
    spec = {"case": dataclasses.asdict(case), "folder": str(folder), "user_dir": USER_DIR}
    script = CHILD.format(tools=str(zoo.ROOT / "tools"), tests=str(zoo.HERE), spec=spec)
    log_path = folder / "child.log"
    folder.mkdir(parents=True, exist_ok=True)
    with open(log_path, "w") as log:
        child = subprocess.Popen([sys.executable, "-c", script], stdout=log,
                                 stderr=subprocess.STDOUT, start_new_session=True)
        try:
            child.wait(timeout=TIMEOUT)
            timed_out = False
        except subprocess.TimeoutExpired:
            os.killpg(child.pid, signal.SIGKILL)   # the case and its command-line child
            child.wait()
            timed_out = True
    records, begun, done = zoo.read_report(folder / "harness" / "report.jsonl")
    violations = [zoo.Violation(**v) for record in records for v in record["violations"]]
    if timed_out:
        violations.append(zoo.Violation(begun or "start", "time",
                                        f"the case did not end within {TIMEOUT:.0f} s"))
    elif child.returncode < 0:
        violations.append(zoo.Violation(begun or "start", "crash",
                                        f"Blender died of signal {-child.returncode}"))
    elif child.returncode != 0 or not done:
        tail = log_path.read_text(errors="replace").strip().splitlines()[-1:] or [""]
        violations.append(zoo.Violation(begun or "start", "crash",
                                        f"the case's Blender ended with code "
                                        f"{child.returncode}: {tail[0][:200]}"))
    return violations


@pytest.mark.parametrize("case", CASES, ids=[case.id for case in CASES])
def test_scene_zoo(case, tmp_path):
    start = time.monotonic()
    violations = run_case(case, tmp_path / "case")
    RESULTS.append((case.id, violations, time.monotonic() - start))
    assert not violations, f"{case.id}:\n" + "\n".join(v.line() for v in violations)


def failure_table(results, product):
    """Markdown: the failing cases grouped by cause (the first broken invariant of each case),
    then every broken invariant (a case may break several), each with its count of cases, one
    example case and the steps where it showed. Numbers and paths are blurred to group."""
    def table(title, rows_of):
        groups = collections.defaultdict(list)
        for case_id, violations, _ in results:
            for v in rows_of(violations):
                groups[(v.invariant, zoo.normalised(v.message))].append((case_id, v))
        rows = [f"### {title}", "", "| cases | invariant: first line (one example) | "
                "example case | steps |", "| ---: | --- | --- | --- |"]
        for found in sorted(groups.values(), key=lambda f: -len({c for c, _ in f})):
            case_id, example = found[0]
            steps = sorted({v.step for _, v in found})
            rows.append(f"| {len({c for c, _ in found})} | {example.invariant}: "
                        f"{example.message.replace('|', '/')} | `{case_id}` | "
                        f"{', '.join(steps[:4])}{' …' if len(steps) > 4 else ''} |")
        return "\n".join(rows) + "\n"
    failed = sum(1 for _, violations, _ in results if violations)
    seconds = sum(s for _, _, s in results)
    return (f"{len(results)} cases (of {product:,} in the full product), {failed} failing, "
            f"{seconds:.0f} s\n\n"
            + table("By cause (each failing case once, by its first failure)",
                    lambda violations: violations[:1]) + "\n"
            + table("Every failure", lambda violations: violations))


@pytest.fixture(scope="module", autouse=True)
def grouped_report():
    yield
    if REPORT and RESULTS:
        product = zoo.product_size(zoo.axis_values(zoo.mesh_modifier_types()))
        with open(REPORT, "w") as f:
            f.write(failure_table(RESULTS, product))


# --- the zoo's own machinery: the sample covers what it claims -------------------------------

def test_every_pair_of_feature_values_meets_in_the_full_zoo():
    values = zoo.axis_values(zoo.mesh_modifier_types())
    drawn = zoo.pairwise(values)
    met = set().union(*(zoo.pairs_of(dataclasses.asdict(case)) for case in drawn))
    assert met >= set(zoo.valid_pairs(values))
    assert all(zoo.is_valid(dataclasses.asdict(case)) for case in drawn)
    assert drawn == zoo.pairwise(values)                  # seeded: the same cases every run
    assert len({case.id for case in drawn}) == len(drawn)
    assert drawn[:zoo.SAMPLE_SIZE] == zoo.cases(full=False)
    # Every value of every axis but the modifier's is in the sample of `make test`.
    for axis in zoo.AXES[1:]:
        assert {getattr(case, axis) for case in drawn[:zoo.SAMPLE_SIZE]} == set(values[axis])
    # Every modifier type Blender adds to a mesh is a value of the modifier axis.
    assert {'NODES', 'HOOK', 'OCEAN', 'SKIN', 'SOLIDIFY', 'REMESH', 'MULTIRES'} <= set(
        zoo.mesh_modifier_types())
    assert not {'GREASE_PENCIL_TINT', 'LINEART'} & set(zoo.mesh_modifier_types())
