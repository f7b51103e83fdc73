"""The header every benchmark prints: the machine, its load, and package versions."""

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
