"""Saved solutions: a solved task written to one ``.npz`` file with a JSON header, and read back.

The file (format ``jaxmm-solution``, version 8) holds NumPy arrays only (no pickles) and one
JSON header ``__header__``:

* ``format``, ``version``, ``jaxmm_version``, ``saved_at`` (UTC, ISO 8601);
* ``robot``: name, optimised joints, jet and contact frames, total mass [kg] and a SHA-256
  ``fingerprint`` of the model's numbers and structure, checked on load;
* ``task``: the scenario name, N, the static options, and the skeleton of its ``params`` and
  ``weights`` (every number is an array of the file);
* ``status`` (name and code), ``message``, ``objective``, ``iterations``, ``violation``,
  ``violation_per_family``: a summary readable without JAX (``read_header``);
* ``trajectory`` and ``solution``: skeletons of the ``Trajectory`` (physical units) and of the
  solver's ``Solution`` (scaled variables, multipliers, bound multipliers, history), enough to
  warm-start a new solve from the loaded result.

Files of versions 1 (before the history recorded the linear solves of each iteration), 2
(before it marked the restoration phase's iterations) and 3 (before it recorded the
factorisations of the inertia correction) are read too: their history gets the missing columns
as NaN. Files before version 5 (before the complementarity's σ and slack bound were task
parameters) solved the published relaxation: σ = 0, ε_max = ∞. Files before version 6 (before
the squared slack penalty was a weight) name their penalty in the task's ``slack_penalty``; it
becomes the weights ``complementarity_slack`` and ``complementarity_slack_squared``. Files
before version 7 (before the planar rows had a σ_t of their own) bounded them by σ_n: their
``planar_tolerance`` is their ``complementarity_tolerance``. Files before version 8 (before
the relaxation homotopy's share on the planar rows was a task parameter) widened both rows alike:
their ``planar_relaxation`` is 1.

Arrays are named by their path in the skeleton (``trajectory.knots.com``). Files are written
atomically: a temporary file in the same directory, renamed over the target once complete.
"""

import dataclasses
import datetime
import hashlib
import importlib.metadata
import json
import os
import tempfile
import zipfile

import jax
import numpy as np

from jaxmm.rigid_body.centroidal import total_mass
from jaxmm.programs import TaskSolution
from jaxmm.solver import interior_point as ip
from jaxmm.transcription.problem import Task, TaskParams, Weights
from jaxmm.transcription.variables import Knot, Trajectory

FORMAT = "jaxmm-solution"
VERSION = 8
READABLE_VERSIONS = (1, 2, 3, 4, 5, 6, 7, 8)
# The task parameters added by a version, with the value every older file solved with: a number,
# or the name of the older parameter that it was (the planar rows' σ_t was the normal rows' σ_n).
_ADDED_PARAMS = {5: dict(complementarity_tolerance=0.0, slack_limit=float("inf")),
                 7: dict(planar_tolerance="complementarity_tolerance"), 8: dict(planar_relaxation=1.0)}
HEADER = "__header__"
_CLASSES = {cls.__name__: cls for cls in (Trajectory, Knot, ip.Solution, ip.Multipliers, TaskParams, Weights)}


class SolutionFileError(ValueError):
    """A file that is not a readable jaxmm solution, or that does not match the robot."""


def _encode(value, path, arrays):
    """A JSON skeleton of ``value`` (registered dataclasses, dicts, tuples, arrays, None); its
    arrays go to ``arrays`` under their dotted path."""
    if value is None:
        return None
    if dataclasses.is_dataclass(value):
        name = type(value).__name__
        if name not in _CLASSES:
            raise TypeError(f"cannot save a {name} (at {path})")
        fields = {f.name: _encode(getattr(value, f.name), f"{path}.{f.name}", arrays) for f in dataclasses.fields(value)}
        return {"class": name, "fields": fields}
    if isinstance(value, dict):
        return {"dict": {str(k): _encode(v, f"{path}.{k}", arrays) for k, v in value.items()}}
    if isinstance(value, (tuple, list)):
        return {"tuple": [_encode(v, f"{path}.{i}", arrays) for i, v in enumerate(value)]}
    if isinstance(value, float):  # a Python number stays one: JAX traces it weakly typed
        return {"float": value}
    arrays[path] = np.asarray(value)
    return {"array": path}


def _decode(skeleton, arrays):
    if skeleton is None:
        return None
    if "class" in skeleton:
        cls = _CLASSES.get(skeleton["class"])
        if cls is None:
            raise SolutionFileError(f"unknown class {skeleton['class']!r} in the file")
        expected = {f.name for f in dataclasses.fields(cls)}
        if set(skeleton["fields"]) != expected:
            raise SolutionFileError(
                f"{cls.__name__} fields in the file {sorted(skeleton['fields'])} differ from this jaxmm's {sorted(expected)}"
            )
        return cls(**{k: _decode(v, arrays) for k, v in skeleton["fields"].items()})
    if "dict" in skeleton:
        return {k: _decode(v, arrays) for k, v in skeleton["dict"].items()}
    if "tuple" in skeleton:
        return tuple(_decode(v, arrays) for v in skeleton["tuple"])
    if "float" in skeleton:
        return float(skeleton["float"])
    key = skeleton["array"]
    if key not in arrays:
        raise SolutionFileError(f"array {key!r} is missing from the file")
    return jax.numpy.asarray(arrays[key])


def _decode_params(skeleton, arrays, version):
    """The ``TaskParams`` of a file's skeleton, the parameters newer than its version given the
    value that version solved with (``_ADDED_PARAMS``)."""
    added = {name: value for since, names in _ADDED_PARAMS.items() if version < since for name, value in names.items()}
    fields = dict(skeleton["fields"], **{name: {"float": v} for name, v in added.items() if not isinstance(v, str)})
    fields.update({name: fields[source] for name, source in added.items() if isinstance(source, str)})
    params = _decode(dict(skeleton, fields=fields), arrays)
    return dataclasses.replace(params, **{name: jax.numpy.asarray(getattr(params, name)) for name in added})


def _decode_weights(skeleton, arrays, spec):
    """The ``Weights`` of a file's skeleton; a file before version 6 has no squared slack weight
    and puts its one slack weight on the penalty its task's ``slack_penalty`` names."""
    if "complementarity_slack_squared" in skeleton["fields"]:
        return _decode(skeleton, arrays)
    weights = _decode(dict(skeleton, fields=dict(skeleton["fields"], complementarity_slack_squared={"float": 0.0})),
                      arrays)
    w = weights.complementarity_slack
    zero = jax.numpy.zeros_like(w)
    linear, squared = (w, zero) if spec.get("slack_penalty", "linear") == "linear" else (zero, w)
    return dataclasses.replace(weights, complementarity_slack=linear, complementarity_slack_squared=squared)


def robot_fingerprint(robot):
    """SHA-256 of a robot's structure (topology, frames) and numbers (every model array)."""
    digest = hashlib.sha256()
    digest.update(repr((robot.model.topology, robot.jet_frames, robot.contact_frames)).encode())
    for leaf in jax.tree_util.tree_leaves((robot.model, robot.standing_configuration)):
        array = np.ascontiguousarray(np.asarray(leaf, dtype=np.float64))
        digest.update(str(array.shape).encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def _robot_header(robot):
    return dict(
        name=robot.name,
        joints=list(robot.model.joint_names),
        jet_frames=list(robot.jet_frames),
        contact_frames=list(robot.contact_frames),
        mass=float(total_mass(robot.model)),
        fingerprint=robot_fingerprint(robot),
    )


def save(path, task, result):
    """Write ``result`` (a ``TaskSolution`` of ``task``) to ``path`` (a ``.npz`` file), atomically.

    Returns the path written. The directory must exist; an existing file is replaced only
    once the new one is complete.
    """
    if not isinstance(task, Task) or not isinstance(result, TaskSolution):
        raise TypeError(f"save(path, task, result) needs a Task and a TaskSolution, got {type(task).__name__}, {type(result).__name__}")
    if result.trajectory.n_knots != task.n_knots:
        raise ValueError(f"the result has {result.trajectory.n_knots} knots, the task {task.n_knots}")
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise FileNotFoundError(f"directory {directory!r} does not exist")
    arrays = {}
    status = result.status
    header = dict(
        format=FORMAT,
        version=VERSION,
        jaxmm_version=importlib.metadata.version("jaxmm"),
        saved_at=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        robot=_robot_header(task.robot),
        task=dict(
            name=task.name,
            n_intervals=task.n_intervals,
            zero_initial_thrust=task.zero_initial_thrust,
            integration=task.integration,
            upper_body_joints=list(task.upper_body_joints),
            joint_torque_limits=task.joint_torque_limits,
            params=_encode(task.params, "task.params", arrays),
            weights=_encode(task.weights, "task.weights", arrays),
        ),
        status=dict(name=status.name, code=int(status)),
        message=status.message,
        objective=float(result.solution.objective),
        iterations=int(result.solution.iterations),
        violation=float(result.solution.violation),
        violation_per_family={k: float(v) for k, v in result.violation_per_family.items()},
        trajectory=_encode(result.trajectory, "trajectory", arrays),
        solution=_encode(result.solution, "solution", arrays),
    )
    arrays[HEADER] = np.array(json.dumps(header))
    descriptor, temporary = tempfile.mkstemp(dir=directory, prefix=f".{os.path.basename(path)}.", suffix=".tmp")
    try:
        with os.fdopen(descriptor, "wb") as file:
            np.savez(file, **arrays)
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, path)
    except BaseException:
        os.unlink(temporary)
        raise
    return path


def _open(path):
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no solution file at {path!r}")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as error:
        raise SolutionFileError(f"{path!r} is not a readable .npz solution file ({error})") from None
    if HEADER not in arrays:
        raise SolutionFileError(f"{path!r} has no jaxmm header: not a jaxmm solution file")
    try:
        header = json.loads(str(arrays.pop(HEADER)))
    except json.JSONDecodeError as error:
        raise SolutionFileError(f"{path!r}: corrupt header ({error})") from None
    if header.get("format") != FORMAT:
        raise SolutionFileError(f"{path!r} is not a jaxmm solution file (format {header.get('format')!r})")
    if header.get("version") not in READABLE_VERSIONS:
        raise SolutionFileError(f"{path!r} has format version {header.get('version')}; this jaxmm reads versions "
                                f"{', '.join(map(str, READABLE_VERSIONS))}")
    return header, arrays


def read_header(path):
    """The JSON header of a saved solution (status, objective, robot, task settings), without
    building any JAX array."""
    return _open(path)[0]


def _default_robot(header):
    from jaxmm.robots import load_ironcub

    robot = load_ironcub()
    jets = tuple(header["robot"]["jet_frames"])
    if not set(jets) <= set(robot.jet_frames):
        return robot
    return dataclasses.replace(robot, jet_frames=jets)


def load(path, robot=None):
    """Read a saved solution: returns ``(task, result)``, a ``Task`` and a ``TaskSolution``.

    robot: the ``Robot`` the solution belongs to (default: the assembled iRonCub, with the jets
    the file used). Raises ``SolutionFileError`` for a corrupt or foreign file and for a file
    saved with another robot (name, joints, frames or numbers differ), naming the difference.
    """
    header, arrays = _open(path)
    robot = _default_robot(header) if robot is None else robot
    saved, ours = header["robot"], _robot_header(robot)
    if saved["fingerprint"] != ours["fingerprint"]:
        differences = [key for key in ("name", "joints", "jet_frames", "contact_frames", "mass") if saved[key] != ours[key]]
        what = ", ".join(f"{key} {saved[key]!r} in the file vs {ours[key]!r}" for key in differences) or "the model's numbers differ"
        raise SolutionFileError(f"{os.fspath(path)!r} was saved with another robot: {what}")
    try:
        spec = header["task"]
        task = Task(
            robot=robot,
            params=_decode_params(spec["params"], arrays, header["version"]),
            weights=_decode_weights(spec["weights"], arrays, spec),
            name=spec["name"],
            n_intervals=int(spec["n_intervals"]),
            zero_initial_thrust=bool(spec["zero_initial_thrust"]),
            integration=spec["integration"],
            upper_body_joints=tuple(spec["upper_body_joints"]),
            joint_torque_limits=bool(spec.get("joint_torque_limits", False)),  # absent before the option existed
        )
        trajectory = _decode(header["trajectory"], arrays)
        solution = _decode(header["solution"], arrays)
        history = np.asarray(solution.history)
        missing = len(ip.HISTORY_COLUMNS) - history.shape[1]  # columns newer than the file
        if missing > 0:
            solution = dataclasses.replace(solution, history=jax.numpy.asarray(
                np.concatenate([history, np.full((history.shape[0], missing), np.nan)], axis=1)))
        families = {k: jax.numpy.asarray(v) for k, v in header["violation_per_family"].items()}
    except (KeyError, TypeError) as error:
        raise SolutionFileError(f"{os.fspath(path)!r}: incomplete header ({error!r})") from None
    if trajectory.n_knots != task.n_knots:
        raise SolutionFileError(f"{os.fspath(path)!r}: trajectory of {trajectory.n_knots} knots for a task of {task.n_knots}")
    return task, TaskSolution(trajectory, solution, families)
