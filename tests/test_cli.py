"""The command line: every command does its job end to end; bad input exits 2 with a message
and writes nothing."""

import argparse
import dataclasses
import io as io_module
import json
import re

import jax
import PIL.Image
import pytest

import jaxmm
from jaxmm.cli import Progress, cache_directory, main


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


def test_scenarios_lists_the_four_published_settings(capsys):
    assert main(["scenarios"]) == 0
    out = capsys.readouterr().out
    for name, knots in (("take-off ", 70), ("take-off-and-landing", 200), ("walk-to-fly", 100), ("jumping", 60)):
        assert re.search(rf"^{name}\s+{knots}\s", out, re.MULTILINE), name


def test_solve_writes_solution_report_figures_and_animation(tmp_path, capsys):
    from jaxmm import io

    out = tmp_path / "run"
    code = main(["solve", "take-off", "--knots", "14", "--out", str(out), "--quiet"])
    printed = capsys.readouterr().out
    assert code == 0, printed
    assert "converged" in printed and "validate: ok" in printed
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "CONVERGED" and summary["validate_ok"] and summary["knots"] == 14
    task, result = io.load(out / "solution.npz")
    assert task.n_intervals == 14 and result.status.name == "CONVERGED"
    assert float(task.params.min_dt) == 0.25 and float(task.params.max_dt) == 0.5  # the published horizon kept
    assert "re-simulated CoM" in (out / "validation.txt").read_text()
    torques = summary["torques"]  # the joint torques the plan needs, named against the URDF's limits
    assert torques["worst_joint"] in task.robot.model.joint_names and torques["largest_load"] > 0
    assert torques["base_force_max"] >= 0 and "joint torques: largest |τ|/τ_max" in printed
    pngs = sorted(p.name for p in out.glob("*.png"))
    assert len(pngs) == 8 and all((out / p).stat().st_size > 10_000 for p in pngs), pngs
    with PIL.Image.open(out / "motion.gif") as gif:
        assert gif.n_frames > 30  # 8 fps over the 3.5–7 s horizon


def test_multistart_ranks_the_guesses_and_writes_the_best_and_its_schedules(tmp_path, capsys):
    """Two sampled guesses of the 14-knot take-off (the queue: the compiled solve of the test
    above): the ranked summary, the best instance's solution and the schedules figure."""
    from jaxmm import io

    out = tmp_path / "multi"
    code = main(["multistart", "take-off", "--knots", "14", "--guesses", "2", "--seed", "3", "--out", str(out), "--quiet"])
    printed = capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["guesses"] == 2 and summary["seed"] == 3 and len(summary["ranking"]) == 2
    assert sorted(r["instance"] for r in summary["ranking"]) == [0, 1]
    best = summary["ranking"][0]
    assert code == (0 if best["status"] == "CONVERGED" and summary["best_validate_ok"] else 1), printed
    assert f"best: instance {best['instance']}" in printed and "2 guesses (seed 3)" in printed
    assert (out / "summary.txt").read_text().startswith("2 instances: ")
    task, result = io.load(out / "best.npz")
    assert task.n_intervals == 14 and float(result.solution.objective) == pytest.approx(best["objective"], rel=1e-12)
    assert sum(len(g["members"]) for g in summary["schedules"]) == 2
    assert (out / "schedules.png").stat().st_size > 5_000


def test_progress_is_shown_on_a_terminal_and_silent_otherwise():
    stream = io_module.StringIO()
    progress = Progress(True, stream)
    with progress.compiling("something") as timer:
        pass
    progress.iteration(4, [5.36e6, 1e-3, 2e-2, 1e-4, 0.5, 0.0, 6.0, 0.0, 1.0])
    progress.iteration(5, [5.37e6, 1e-3, 2e-2, 1e-4, 0.5, 3e-3, 1.0, 1.0, 2.5])  # a restoration iteration
    with pytest.raises(ValueError, match="a history row has 9 entries"):
        progress.iteration(6, [5.37e6, 1e-3, 2e-2, 1e-4, 0.5, 3e-3, 1.0, 1.0])
    progress.done()
    text = stream.getvalue()
    assert "compiled something in" in text and timer.seconds >= 0
    assert "iteration     5  objective 5.360000e+06  violation 1.0e-03" in text
    assert "iteration     6r objective 5.370000e+06" in text
    assert text.rstrip().endswith("regularisation 3e-03  factorisations 2.50  solves 1")
    assert Progress.detect(quiet=False) is False  # pytest captures stderr: not a terminal
    quiet = io_module.StringIO()
    silent = Progress(False, quiet)
    with silent.compiling("something"):
        pass
    silent.done()
    assert quiet.getvalue() == ""


def test_compare_prints_both_solvers_side_by_side(solved_take_off, capsys, monkeypatch):
    """The comparison's plumbing: our side is the solved take-off (test_solve_task cross-checks
    the two optima), IPOPT runs for real from the same guess, stopped after 3 iterations."""
    from jaxmm import programs

    monkeypatch.setattr(programs, "compile_solve", lambda task, **kwargs: lambda: solved_take_off[1])
    assert main(["compare", "take-off", "--knots", "14", "--max-iterations", "3", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"status\s+CONVERGED\s+Maximum_Iterations_Exceeded", out), out
    assert re.search(rf"iterations\s+{int(solved_take_off[1].solution.iterations)}\s+3\s", out), out
    assert re.search(r"validate\s+ok\s+FAILED", out), out
    assert "IPOPT solve time / ours" in out


@pytest.mark.parametrize("argv, message", [
    (["solve", "hover"], "unknown scenario 'hover'"),
    (["solve", "take-off", "--target", "9", "0", "0.8", "--no-figures"], "outside the workspace"),
    (["solve", "take-off", "--urdf", "/no/such.urdf"], "URDF file not found: /no/such.urdf"),
    (["multistart", "hover", "--guesses", "2"], "unknown scenario 'hover'"),
])
def test_solve_rejects_bad_input_with_a_message_and_no_output(argv, message, tmp_path, capsys):
    assert main(argv + ["--out", str(tmp_path / "out")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_a_cache_directory_that_is_a_file_is_named_and_nothing_is_written(tmp_path, capsys):
    occupied = tmp_path / "occupied"
    occupied.write_text("")
    assert main(["solve", "take-off", "--cache-dir", str(occupied), "--out", str(tmp_path / "out")]) == 2
    assert f"compilation cache directory {occupied} exists and is not a directory" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
    with pytest.raises(SystemExit) as exit:
        main(["solve", "take-off", "--cache-dir", str(tmp_path), "--no-cache"])
    assert exit.value.code == 2 and "not allowed with" in capsys.readouterr().err


def test_the_cache_directory_a_command_uses(tmp_path, monkeypatch):
    from jaxmm import compilation

    solve = dict(cache_dir=None, no_cache=False)
    assert cache_directory(argparse.Namespace(**dict(solve, cache_dir=str(tmp_path)))) == tmp_path
    assert cache_directory(argparse.Namespace(**dict(solve, no_cache=True))) is None
    assert cache_directory(argparse.Namespace()) is None  # `robot`, `scenarios`: nothing to compile
    saved = jax.config.jax_compilation_cache_dir  # read only: no cache is re-pointed here
    try:
        jax.config.update("jax_compilation_cache_dir", str(tmp_path / "jax"))
        assert cache_directory(argparse.Namespace(**solve)) == tmp_path / "jax"  # JAX's own setting first
        jax.config.update("jax_compilation_cache_dir", None)
        monkeypatch.setenv("JAXMM_CACHE_DIR", str(tmp_path / "mine"))
        assert cache_directory(argparse.Namespace(**solve)) == compilation.default_cache_directory() == tmp_path / "mine"
    finally:
        jax.config.update("jax_compilation_cache_dir", saved)


def test_knots_below_two_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as exit:
        main(["solve", "take-off", "--knots", "1"])
    assert exit.value.code == 2 and "--knots must be at least 2" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit:
        main(["multistart", "take-off", "--guesses", "0"])
    assert exit.value.code == 2 and "--guesses must be at least 1" in capsys.readouterr().err


def test_relaxation_sets_the_solver_option_and_a_negative_one_is_a_usage_error(capsys):
    from jaxmm import cli, programs

    args = argparse.Namespace(max_iterations=None, ipopt_slacks=False, relaxation=2e-3)
    assert cli.solver_options(args) == dataclasses.replace(programs.DEFAULT_OPTIONS, relaxation=2e-3)
    # --exact solves with the exact task's settings (the homotopy, μ × 0.7 per barrier problem);
    # --relaxation replaces their κ_σ (0: off)
    exact = argparse.Namespace(**{**vars(args), "relaxation": None, "exact": 1e-6})
    assert cli.solver_options(exact) == programs.EXACT_OPTIONS and programs.EXACT_OPTIONS.relaxation > 0
    assert programs.EXACT_OPTIONS.barrier_factor == 0.7 and programs.EXACT_OPTIONS.barrier_power == 1.0
    assert cli.solver_options(argparse.Namespace(**{**vars(exact), "relaxation": 0.0})) == dataclasses.replace(
        programs.EXACT_OPTIONS, relaxation=0.0)
    assert cli.solver_options(argparse.Namespace(**{**vars(exact), "exact": None})) == programs.DEFAULT_OPTIONS
    with pytest.raises(SystemExit) as exit:
        main(["solve", "take-off", "--relaxation", "-1"])
    assert exit.value.code == 2 and "--relaxation must be a finite number ≥ 0" in capsys.readouterr().err


def test_exact_solves_the_exact_task_and_a_negative_sigma_is_a_usage_error(capsys):
    from jaxmm import cli, tasks

    args = argparse.Namespace(scenario="take-off", knots=14, target=None, urdf=None, torque_limits=False, exact=1e-6,
                              planar_tolerance=None)
    exact = cli.scenario_task(args)
    assert float(exact.params.complementarity_tolerance) == 1e-6 and float(exact.params.slack_limit) == 0.0
    assert float(exact.params.planar_tolerance) == tasks.PLANAR_TOLERANCE
    planar = cli.scenario_task(argparse.Namespace(**{**vars(args), "planar_tolerance": 3e-6}))
    assert float(planar.params.planar_tolerance) == 3e-6 and float(planar.params.complementarity_tolerance) == 1e-6
    published = cli.scenario_task(argparse.Namespace(**{**vars(args), "exact": None}))
    assert float(published.params.complementarity_tolerance) == 0.0 and float(published.params.slack_limit) == float("inf")
    assert float(published.params.planar_tolerance) == 0.0
    for argv, message in ((["--exact", "-1"], "--exact must be a finite number ≥ 0"),
                          (["--exact", "--planar-tolerance", "inf"], "--planar-tolerance must be a finite number ≥ 0"),
                          (["--planar-tolerance", "1e-4"], "--planar-tolerance applies to the exact task")):
        with pytest.raises(SystemExit) as exit:
            main(["solve", "take-off", *argv])
        assert exit.value.code == 2 and message in capsys.readouterr().err


def test_an_unconverged_solve_is_written_and_reported_with_exit_1(solved_take_off, tmp_path, capsys, monkeypatch):
    """The outputs of a solve that stopped early and fails validate: written all the same, the
    failure named in the summary, exit status 1."""
    from jaxmm import programs
    from jaxmm.solver import interior_point as ip

    _, result = solved_take_off
    knots = result.trajectory.knots
    stopped = dataclasses.replace(
        result,
        trajectory=dataclasses.replace(result.trajectory, knots=dataclasses.replace(knots, com=knots.com + 0.05)),
        solution=dataclasses.replace(result.solution, status=jax.numpy.asarray(int(ip.Status.MAX_ITERATIONS))),
    )
    monkeypatch.setattr(programs, "compile_solve", lambda task, **kwargs: lambda: stopped)
    out = tmp_path / "run"
    assert main(["solve", "take-off", "--knots", "14", "--out", str(out), "--quiet", "--no-figures"]) == 1
    printed = capsys.readouterr().out
    assert "stopped at the iteration limit" in printed and "validate: FAILED: " in printed
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "MAX_ITERATIONS" and not summary["validate_ok"]
    assert "initial CoM at target" in summary["failed_checks"]
    assert (out / "solution.npz").is_file() and not list(out.glob("*.png"))
