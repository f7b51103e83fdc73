"""Every notebook runs top to bottom (nbclient), at reduced sizes set through its ``parameters``
cell, so that none of them rots. The notebooks as committed keep the outputs of their own
(larger) parameters."""

import pathlib

import nbclient
import nbformat
import pytest

NOTEBOOKS = pathlib.Path(__file__).resolve().parents[1] / "notebooks"

# Appended to each notebook's parameters cell: the smallest sizes at which every cell still
# does its job (the 14-knot take-off is the problem the test suite already compiles).
CI_PARAMETERS = {
    "01_robot_model": "SAMPLES = 5",
    "02_take_off": "KNOTS = 14",
    # the take-off the CI main job compiles; the other scenarios go through the same cells
    "03_all_scenarios": "KNOTS = {'take_off': 14}",
    "04_multistart": "KNOTS = 14\nGUESSES = 2\nMAX_ITERATIONS = 25",
    "05_weight_tuning": "KNOTS = 14\nSTEPS = 1\nLANDING_KNOTS = 20",
    # IPOPT stopped early: test_solve_task cross-checks the converged optima; here every cell runs
    "06_ipopt_reference": "KNOTS = 14\nIPOPT_MAX_ITERATIONS = 10",
}


def test_every_notebook_has_ci_parameters():
    assert sorted(p.stem for p in NOTEBOOKS.glob("*.ipynb")) == sorted(CI_PARAMETERS)


def _run(name, directory):
    notebook = nbformat.read(NOTEBOOKS / f"{name}.ipynb", as_version=4)
    parameters = [c for c in notebook.cells if "parameters" in c.metadata.get("tags", [])]
    assert len(parameters) == 1, f"{name}: one cell tagged 'parameters' sets the sizes"
    parameters[0].source += "\n# CI sizes (tests/test_notebooks.py)\n" + CI_PARAMETERS[name]
    client = nbclient.NotebookClient(
        notebook, timeout=1800, kernel_name="python3", resources={"metadata": {"path": str(directory)}}
    )
    client.execute()  # raises CellExecutionError, with the cell and its traceback, on any error
    errors = [o for c in notebook.cells if c.cell_type == "code" for o in c.get("outputs", []) if o.output_type == "error"]
    assert not errors


# The tuning studies solve and differentiate a dozen times even at CI sizes (10 minutes on one
# core), and the multistart notebook compiles a vmapped batch of robot solves (minutes): like
# the other robot-scale batch and tuning tests, they run by hand with ``pytest -m slow``. So does
# the IPOPT notebook (about 85 s of building the CasADi NLP and compiling), whose comparison ``test_solve_task``'s IPOPT cross-checks make on converged optima,
# and the all-scenarios notebook (53 s; at CI sizes the take-off that 02 solves).
SLOW = {"03_all_scenarios", "04_multistart", "05_weight_tuning", "06_ipopt_reference"}


def _notebook_test(name):
    def test_runs_top_to_bottom(self, tmp_path):
        _run(name, tmp_path)

    if name in SLOW:
        test_runs_top_to_bottom = pytest.mark.slow(test_runs_top_to_bottom)

    return type(f"TestNotebook_{name}", (), {"test_runs_top_to_bottom": test_runs_top_to_bottom})


# One class per notebook: pytest-xdist's --dist loadscope sends each class to a worker of its
# own, so the notebooks spread over both workers (a file would keep them on one).
for _name in CI_PARAMETERS:
    globals()[f"TestNotebook_{_name}"] = _notebook_test(_name)
