"""What every benchmark shares: the header (the machine, its load, package versions) and the
format of a duration."""

import importlib.metadata
import os
import platform


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
