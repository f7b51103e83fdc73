"""``tools/torques.py``: its tables of a saved plan agree with ``analysis.joint_torques``."""

import importlib.util
import pathlib

import numpy as np

from jaxmm import analysis, io

ROOT = pathlib.Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("torques_tool", ROOT / "tools" / "torques.py")
torques_tool = importlib.util.module_from_spec(spec)
spec.loader.exec_module(torques_tool)


def test_the_tables_name_the_worst_joint_and_every_limited_joint(solved_take_off, tmp_path, capsys):
    task, result = solved_take_off
    path = io.save(tmp_path / "solution.npz", task, result)
    assert torques_tool.main([path, path]) == 0
    printed = capsys.readouterr().out
    report = analysis.joint_torques(task, result.trajectory)
    name, knot, torque, limit = report.worst
    assert f"{name}, knot {knot}: {torque:.1f} / {limit:g} N m" in printed
    limited = [j for j, effort in zip(report.joint_names, report.effort_limits) if effort < 1000]
    assert limited and all(f"| {j} " in printed for j in limited)  # the legs: 55.5 and 37 N m
    assert not any(f"| {j} " in printed for j in report.joint_names if j not in limited)
    hip = report.joint_names.index(limited[0])
    assert f"{np.abs(report.torques[:, hip]).max():.1f}" in printed
