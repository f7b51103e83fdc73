"""Every benchmark at a reduced size, one after another, into one JSON record, so that runs
can be compared over time (``--compare`` prints the ratios against an earlier record).

The benchmarks run as they would by hand (each script in its own process, its Markdown tables on
stdout); this entry parses those tables into records (header → cell, and durations such as
"12.3 ms" also as seconds) and adds the machine, the versions, the git commit, the command
line and the wall time of each benchmark. The processes run in turn, never two at once: two JAX
processes on the same cores slow each other down many times over (see the README).

Usage:
    python benchmarks/regression.py [--out benchmarks/results/regression-<date>.json]
                                    [--only rigid_body solve ...] [--compare earlier.json]

Reduced sizes (24 minutes on the 2-core machine, compiling included):
"""

import argparse
import datetime
import importlib.metadata
import json
import os
import pathlib
import platform
import re
import subprocess
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent

# name: (script, arguments at the reduced size)
BENCHMARKS = {
    "rigid_body": ("rigid_body.py", ["--batch", "64", "--repeats", "3", "--eager-repeats", "1", "--budget", "30"]),
    "transcription": ("transcription.py", ["--knots", "14", "--repeats", "3"]),
    "solve": ("solve_scenarios.py", ["--scenarios", "take_off", "--knots-override", "14", "--repeats", "1"]),
    "batched": ("batched.py", ["--knots", "14", "--sizes", "1", "2", "--sequential", "2"]),
    "tuning": ("tuning.py", ["--knots", "14", "--steps", "2"]),
}
__doc__ += "".join(f"    {name}: {script} {' '.join(arguments)}\n" for name, (script, arguments) in BENCHMARKS.items())

PACKAGES = ("jax", "jaxlib", "numpy", "optax", "casadi", "pin")
_DURATION = re.compile(r"^≈?\s*([0-9.]+(?:e[-+]?\d+)?)\s*(µs|ms|s)$")
_UNITS = {"µs": 1e-6, "ms": 1e-3, "s": 1.0}


def seconds(cell):
    """A duration cell ("12.3 ms", "≈ 4.1 s") in seconds, or None."""
    match = _DURATION.match(cell.strip())
    return float(match.group(1)) * _UNITS[match.group(2)] if match else None


def parse_tables(text):
    """The Markdown tables of ``text`` as lists of {column: cell}, durations also as
    "<column> [s]" numbers."""
    tables, lines = [], text.splitlines()
    i = 0
    while i + 1 < len(lines):
        if lines[i].startswith("|") and re.match(r"^\|[-| :]+\|$", lines[i + 1].strip()):
            header = [c.strip() for c in lines[i].strip().strip("|").split("|")]
            rows, i = [], i + 2
            while i < len(lines) and lines[i].startswith("|"):
                cells = [c.strip() for c in lines[i].strip().strip("|").split("|")]
                row = dict(zip(header, cells))
                row.update({f"{k} [s]": seconds(v) for k, v in list(row.items()) if seconds(v) is not None})
                rows.append(row)
                i += 1
            tables.append(rows)
        else:
            i += 1
    return tables


def machine():
    """The machine, its load and the versions."""
    with open("/proc/cpuinfo") as cpuinfo:
        cpu = next((line.split(":", 1)[1].strip() for line in cpuinfo if line.startswith("model name")),
                   platform.processor())
    versions = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=HERE, capture_output=True, text=True,
                                check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = None
    return dict(cpu=cpu, cores=os.cpu_count(), load_average=os.getloadavg(), platform=platform.platform(),
                versions=versions, commit=commit)


def run(name, script, arguments):
    """One benchmark in its own process: its record."""
    print(f"{name}: python {script} {' '.join(arguments)}", file=sys.stderr, flush=True)
    start = time.perf_counter()
    done = subprocess.run([sys.executable, str(HERE / script), *arguments], cwd=HERE, capture_output=True, text=True,
                          env=dict(os.environ, OPENBLAS_NUM_THREADS="1"))
    wall = time.perf_counter() - start
    print(f"{name}: exit {done.returncode} after {wall:.0f} s", file=sys.stderr, flush=True)
    return dict(command=[script, *arguments], exit_code=done.returncode, wall_seconds=wall,
                tables=parse_tables(done.stdout), stdout=done.stdout,
                stderr_tail=done.stderr.splitlines()[-20:] if done.returncode else [])


def durations(record):
    """{(benchmark, table, row, column): seconds} of a record."""
    found = {}
    for name, bench in record["benchmarks"].items():
        for t, table in enumerate(bench["tables"]):
            for r, row in enumerate(table):
                label = next(iter(row.values()), str(r))
                for column, value in row.items():
                    if column.endswith(" [s]") and value is not None:
                        found[(name, t, label, column)] = value
    return found


def compare(new, old):
    """Lines "benchmark / row / column: old → new (ratio)" for the durations both records have."""
    a, b = durations(old), durations(new)
    lines = []
    for key in sorted(set(a) & set(b), key=str):
        ratio = b[key] / a[key] if a[key] else float("inf")
        name, table, label, column = key
        flag = "  <-- slower" if ratio > 1.5 else ""
        lines.append(f"{name} table {table} [{label}] {column}: {a[key]:.3g} → {b[key]:.3g} s ({ratio:.2f}×){flag}")
    return lines


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    parser.add_argument("--out", default=str(HERE / "results" / f"regression-{stamp}.json"), help="JSON file to write")
    parser.add_argument("--only", nargs="+", choices=list(BENCHMARKS), help="run only these benchmarks")
    parser.add_argument("--compare", help="an earlier record: print the ratios of every duration")
    args = parser.parse_args()
    record = dict(format="jaxmm-benchmark-record", version=1, started=stamp, machine=machine(), benchmarks={})
    for name in args.only or BENCHMARKS:
        record["benchmarks"][name] = run(name, *BENCHMARKS[name])
    record["load_average_at_end"] = os.getloadavg()
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    temporary = out.with_name(f".{out.name}.tmp")
    temporary.write_text(json.dumps(record, indent=1) + "\n")
    os.replace(temporary, out)
    failed = [name for name, bench in record["benchmarks"].items() if bench["exit_code"]]
    print(f"wrote {out}: {len(record['benchmarks'])} benchmarks"
          + (f", FAILED: {', '.join(failed)}" if failed else ", all exited 0"))
    if args.compare:
        print("\n".join(compare(record, json.loads(pathlib.Path(args.compare).read_text()))))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
