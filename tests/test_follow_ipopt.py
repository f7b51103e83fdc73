"""``tools/follow_ipopt.py``'s reader of IPOPT's iteration log."""

import importlib.util
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))  # follow_ipopt.py imports benchmarks/machine.py
spec = importlib.util.spec_from_file_location("follow_ipopt", ROOT / "tools" / "follow_ipopt.py")
follow_ipopt = importlib.util.module_from_spec(spec)
spec.loader.exec_module(follow_ipopt)

LOG = """\
iter    objective    inf_pr   inf_du lg(mu)  ||d||  lg(rg) alpha_du alpha_pr  ls
   0  6.0070347e+05 3.73e+02 1.00e+02  -1.0 0.00e+00    -  0.00e+00 0.00e+00   0
   1  6.0097044e+05 3.73e+02 1.00e+02  -1.0 2.90e+01    -  4.99e-04 1.02e-04f  1
   6  8.2499025e+05 3.57e+02 3.35e+02  -1.0 3.27e+01   0.0 9.03e-04 4.42e-03f  1
  42r 1.2345678e+06 2.00e+01 9.99e+02   0.5 1.00e+00  -2.5 1.00e+00 5.00e-01h  3

Number of Iterations....: 160
Objective...............:   8.5737465255003066e+02    5.1442507549064085e+06
"""


def test_iteration_rows_are_read_with_restoration_marks_and_the_start_left_out():
    rows = follow_ipopt.ipopt_iterations(LOG)
    assert rows == [
        (1, False, 600970.44, 373.0, "-", "1.02e-04f"),
        (6, False, 824990.25, 357.0, "0.0", "4.42e-03f"),
        (42, True, 1234567.8, 20.0, "-2.5", "5.00e-01h"),
    ]
