"""What every benchmark shares: the header (the machine, its load, package versions), the
format of a duration, progress lines, a wall-clock timer, Markdown tables and measurements run
in a fresh Python process."""

import importlib.metadata
import json
import os
import platform
import subprocess
import sys
import time


def machine_lines(packages):
    """Two lines: CPU model, cores and load average; versions of python and of ``packages``."""
    with open("/proc/cpuinfo") as cpuinfo:
        cpu = next(
            (line.split(":", 1)[1].strip() for line in cpuinfo if line.startswith("model name")),
            platform.processor(),
        )
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    versions = ", ".join(f"{name} {importlib.metadata.version(name)}" for name in packages)
    return [
        f"machine: {cpu}, {os.cpu_count()} cores, load average {load} (1, 5, 15 min) at start",
        f"versions: python {platform.python_version()}, {versions}",
    ]


def format_time(value):
    """A duration [s] in µs, ms or s with three significant digits; "–" for None."""
    if value is None:
        return "–"
    if value < 1e-3:
        return f"{value * 1e6:.3g} µs"
    if value < 1:
        return f"{value * 1e3:.3g} ms"
    return f"{value:.3g} s"


def log(message):
    """A progress line on stderr (the tables go to stdout)."""
    print(message, file=sys.stderr, flush=True)


def timed(run):
    """(result, wall seconds) of run()."""
    start = time.perf_counter()
    result = run()
    return result, time.perf_counter() - start


def render(header, rows):
    """A Markdown table."""
    lines = [tuple(header)] + [tuple(map(str, row)) for row in rows]
    widths = [max(len(line[i]) for line in lines) for i in range(len(header))]
    cells = lambda line: "| " + " | ".join(c.ljust(w) for c, w in zip(line, widths)) + " |"  # noqa: E731
    return "\n".join([cells(lines[0]), "|" + "|".join("-" * (w + 2) for w in widths) + "|"] + list(map(cells, lines[1:])))


def probe(code, arguments, what, **environment):
    """Run ``code`` in a fresh Python process with ``arguments`` (``sys.argv[1:]``) and
    ``environment`` added to this one's (OPENBLAS_NUM_THREADS=1 unless given); returns the JSON
    of its last line that starts with "PROBE ". Raises RuntimeError naming ``what`` on failure."""
    env = dict(os.environ, **{"OPENBLAS_NUM_THREADS": "1", **environment})
    result = subprocess.run([sys.executable, "-c", code, *map(str, arguments)], capture_output=True, text=True, env=env)
    lines = [line for line in result.stdout.splitlines() if line.startswith("PROBE ")]
    if result.returncode or not lines:
        raise RuntimeError(f"{what} failed:\n{result.stderr[-3000:]}")
    return json.loads(lines[-1][len("PROBE "):])
