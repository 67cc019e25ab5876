"""Before and after in one bench run: child cases measured with the solver of a baseline revision
and with the current one, back to back, so their ratio is read under the same load.

The baseline's ``solver`` package is exported from git (``git archive``) into a temporary folder
and put first on the child's ``PYTHONPATH``; the case code itself is the current bench's, so a
compared case must call solver functions that exist at both revisions (a case that cannot run on
the baseline shows its error in the table instead of a ratio).
"""

import contextlib
import io
import math
import os
import re
import subprocess
import tarfile
import tempfile


@contextlib.contextmanager
def exported_solver(root, revision):
    """A folder holding ``solver/`` as it was at ``revision`` of the repository at ``root``."""
    archive = subprocess.run(["git", "-C", str(root), "archive", "--format=tar", revision,
                              "solver"], capture_output=True, check=True).stdout
    with tempfile.TemporaryDirectory(prefix="rs_elastic_baseline_") as folder:
        with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
            tar.extractall(folder, filter="data")
        yield folder


def child_environment(solver_root, deps):
    """The environment of a child that imports ``solver`` from ``solver_root``."""
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(solver_root), str(deps)])}


LABEL_FIELDS = ("modes", "frames", "material", "size", "integrator")   # name a list's rows


def entry_label(entry, index):
    """How a row of a list is named in a key: its identifying fields, else its index."""
    fields = [f"{k}={entry[k]}" for k in LABEL_FIELDS if k in entry]
    return ",".join(fields) if fields else str(index)


def numeric_items(row, prefix=""):
    """{dotted key: number} of a JSON row; a list of rows flattened as key[label].figure."""
    items = {}
    for key, value in row.items():
        name = f"{prefix}{key}"
        if isinstance(value, (int, float)) and math.isfinite(value):     # a bool as 0 or 1
            items[name] = float(value)
        elif isinstance(value, dict):
            items.update(numeric_items(value, name + "."))
        elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            for i, entry in enumerate(value):
                items.update(numeric_items(entry, f"{name}[{entry_label(entry, i)}]."))
    return items


def key_pattern(key):
    """A compiled pattern of a dotted key in which '*' stands for any text (a list index)."""
    return re.compile(".*".join(re.escape(part) for part in key.split("*")) + "$")


def compared(pair, keys):
    """[(key, baseline, current, current / baseline)] of the figures both rows have whose
    dotted key matches one of ``keys`` ('*' matches any text, e.g. rows[*].seconds)."""
    base, current = numeric_items(pair["baseline"]), numeric_items(pair["current"])
    patterns = [key_pattern(k) for k in keys]
    out = []
    for key in sorted(set(base) & set(current), key=natural_order):
        if any(p.match(key) for p in patterns):
            ratio = current[key] / base[key] if base[key] else float("nan")
            out.append((key, base[key], current[key], ratio))
    return out


def natural_order(key):
    """Sort key that puts rows[10] after rows[9]."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", key)]


def comparison_table(pairs, revision):
    """Markdown: one line per compared figure, baseline against current, and their ratio."""
    lines = [f"## Before and after, one run (baseline: solver of {revision})", "",
             "| case | figure | baseline | current | current / baseline |", "|---|---|---|---|---|"]
    for pair in pairs:
        label = f"{pair['case']} {pair['arg']}"
        errors = [f"{side}: {pair[side]['error']}" for side in ("baseline", "current")
                  if "error" in pair[side]]
        if errors:
            lines.append(f"| {label} | error | {'; '.join(errors)} | | |")
            continue
        for key, before, after, ratio in compared(pair, pair["keys"]):
            lines.append(f"| {label} | {key} | {before:.4g} | {after:.4g} | {ratio:.3g} |")
    return "\n".join(lines) + "\n"
