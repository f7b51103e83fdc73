"""The default robot: the jet-powered iCub (iRonCub) assembled at load time from a base URDF and
the description ``assets/ironcub.toml`` (frames on fixed joints, subtrees removed), so that no
URDF is edited by hand. The same description format assembles any other robot from any URDF.
"""

import importlib.resources
import tomllib

from jaxmm.rigid_body.configuration import make_configuration
from jaxmm.robots.robot import edit_urdf, load_robot

ASSETS = importlib.resources.files("jaxmm.assets")


def _base_urdf(base):
    """The base URDF that a description's ``[base]`` table names: ``urdf`` (a path) or
    ``icub_model`` (a model of the icub-models package)."""
    if "urdf" in base:
        return base["urdf"]
    import icub_models

    return icub_models.get_model_file(base["icub_model"])


def assemble_urdf(description=None, base=None):
    """A ``yourdfpy.URDF`` from a base URDF and a description (a parsed TOML dict; default:
    iRonCub's, ``ironcub_description()``).

    base: any URDF (path, XML string or ``yourdfpy.URDF``); default: the one the description's
    ``[base]`` table names (``urdf = "path"`` or ``icub_model = "name"``). The base's subtrees
    listed in ``base.remove_subtrees`` are removed, then each ``[[frames]]`` entry (the fields of
    ``robots.Frame``) is added as a link on a fixed joint, with its inertia if it has a mass.
    """
    description = ironcub_description() if description is None else description
    table = description.get("base", {})
    source = _base_urdf(table) if base is None else base
    return edit_urdf(source, description.get("frames", ()), table.get("remove_subtrees", ()), description["name"])


def ironcub_description():
    """The parsed ``assets/ironcub.toml`` description of the jet-powered iCub."""
    with (ASSETS / "ironcub.toml").open("rb") as stream:
        return tomllib.load(stream)


def load_ironcub(joints=None, locked=None):
    """The default robot: iRonCub assembled from icub-models' iCubGazeboV2_5 and ``assets/``.

    joints, locked: override the description's 23 optimised joints and locked neck; the
    standing configuration keeps the published values of the joints that remain optimised.
    """
    description = ironcub_description()
    joints = description["joints"]["optimised"] if joints is None else list(joints)
    locked = description["joints"].get("locked", {}) if locked is None else locked
    standing = description["standing"]
    published = dict(zip(description["joints"]["optimised"], standing["joint_positions"]))
    q = make_configuration(
        standing["base_position"],
        standing["base_quaternion"],
        [published.get(joint, 0.0) for joint in joints],
    )
    return load_robot(
        assemble_urdf(description),
        joints=joints,
        locked=locked,
        jet_frames=description["jets"]["frames"],
        contact_frames=description["contacts"]["frames"],
        standing_configuration=q,
        name=description["name"],
        reference_mass=description.get("reference_mass_kg"),
    )
