"""Robots: ``load_robot`` for any URDF (with frames added and subtrees removed at load time),
and the default robot, iRonCub, assembled from icub-models (``load_ironcub``). Link meshes for
drawing are in ``jaxmm.robots.meshes``."""

from jaxmm.robots.ironcub import assemble_urdf, ironcub_description, load_ironcub
from jaxmm.robots.robot import Frame, Robot, edit_urdf, load_robot

__all__ = ["Frame", "Robot", "assemble_urdf", "edit_urdf", "ironcub_description", "load_ironcub", "load_robot"]
