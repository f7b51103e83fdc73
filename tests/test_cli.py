"""The command line: `jaxmm robot` prints the summary; bad input exits 2 with a message."""

import re

import jaxmm
from jaxmm.cli import main


def test_robot_summary_of_default_robot(capsys):
    assert main(["robot"]) == 0
    out = capsys.readouterr().out
    mass = float(re.search(r"mass\s+([\d.]+) kg", out).group(1))
    assert abs(mass - float(jaxmm.total_mass(jaxmm.load_ironcub().model))) < 1e-3
    assert "real robot 44.726 kg" in out
    assert "23 optimised, 3 locked" in out
    assert "l_arm_jet_turbine" in out and "r_sole_4" in out
    assert re.search(r"CoM standing\s+\[", out)


def test_robot_summary_of_a_missing_urdf(capsys):
    assert main(["robot", "--urdf", "/no/such.urdf"]) == 2
    assert "URDF file not found: /no/such.urdf" in capsys.readouterr().err
