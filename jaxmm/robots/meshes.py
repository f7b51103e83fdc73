"""Link meshes of a robot in the frames of its bodies, for drawing (``jaxmm.analysis.animation``).

The meshes are the URDF's visual elements. ``package://name/path`` URIs are looked up under the
URDF's folder and its ancestors and under icub-models' shared data, where the iCub meshes of the
default robot live. Each mesh is simplified by vertex clustering (vertices merged on a grid of
``resolution`` metres): a whole iCub keeps ~10k of its 270k triangles at 2 cm, so that a frame
draws in well under a second. Loading is lazy and cached per URDF and resolution.
"""

import dataclasses
import functools
import pathlib

import numpy as np

from jaxmm.robots.ironcub import assemble_urdf, ironcub_description
from jaxmm.rigid_body.urdf import read_urdf

RESOLUTION = 0.02  # [m] grid of the vertex clustering
DEFAULT_COLOUR = (0.75, 0.75, 0.75)


class MeshNotFoundError(FileNotFoundError):
    """A visual mesh of the URDF that cannot be found or read."""


@dataclasses.dataclass(frozen=True)
class RobotMesh:
    """Every visual of a robot as one triangle mesh, each vertex fixed in one body's frame.

    vertices: (nv, 3) [m] in the frame of body vertex_body (nv,); faces: (nf, 3) vertex
    indices; face_colours: (nf, 3) RGB in [0, 1].
    """

    vertices: np.ndarray
    vertex_body: np.ndarray
    faces: np.ndarray
    face_colours: np.ndarray

    def triangles(self, body_rotations, body_positions):
        """World triangles (nf, 3, 3) [m] for body poses (nb, 3, 3), (nb, 3) [m]."""
        R, p = np.asarray(body_rotations)[self.vertex_body], np.asarray(body_positions)[self.vertex_body]
        world = np.einsum("vij,vj->vi", R, self.vertices) + p
        return world[self.faces]


def cluster_vertices(vertices, faces, resolution):
    """Simplify a triangle mesh by merging the vertices of each cube of side resolution [m]
    into their mean and dropping the triangles that collapse or repeat.
    (nv, 3), (nf, 3) → (nv', 3), (nf', 3), winding kept."""
    cells = np.floor(vertices / resolution).astype(np.int64)
    _, cluster = np.unique(cells, axis=0, return_inverse=True)
    cluster = cluster.ravel()
    count = np.bincount(cluster)
    merged = np.zeros((count.size, 3))
    np.add.at(merged, cluster, vertices)
    merged /= count[:, None]
    new_faces = cluster[faces]
    proper = (new_faces[:, 0] != new_faces[:, 1]) & (new_faces[:, 1] != new_faces[:, 2]) & (new_faces[:, 0] != new_faces[:, 2])
    new_faces = new_faces[proper]
    _, first = np.unique(np.sort(new_faces, axis=1), axis=0, return_index=True)
    return merged, new_faces[np.sort(first)]


def _icub_share():
    import icub_models

    return icub_models.get_models_path().parent.parent  # share/, holding iCub/meshes


def resolve_mesh(filename, folder):
    """Path of a URDF mesh filename (``package://``, ``file://`` or relative to folder).
    Raises MeshNotFoundError listing where it looked."""
    if filename.startswith("package://"):
        package, _, rest = filename[len("package://"):].partition("/")
        roots = [folder, *folder.parents] if folder is not None else []
        roots.append(_icub_share())
        candidates = [root / package / rest for root in roots] + [root / rest for root in roots]
    elif filename.startswith("file://"):
        candidates = [pathlib.Path(filename[len("file://"):])]
    else:
        candidates = [(folder or pathlib.Path.cwd()) / filename]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    raise MeshNotFoundError(f"mesh {filename!r} not found (looked for {', '.join(map(str, candidates[:4]))}, …)")


def _geometry(geometry, folder):
    """A trimesh.Trimesh of a URDF visual geometry, in the visual's frame [m]."""
    import trimesh

    if geometry.mesh is not None:
        path = resolve_mesh(geometry.mesh.filename, folder)
        try:
            mesh = trimesh.load(path, force="mesh")
        except Exception as error:  # trimesh raises many kinds for unreadable files
            raise MeshNotFoundError(f"cannot read mesh {path}: {error}") from error
        scale = geometry.mesh.scale if geometry.mesh.scale is not None else 1.0
        mesh.apply_scale(scale)
        return mesh
    if geometry.box is not None:
        return trimesh.creation.box(extents=geometry.box.size)
    if geometry.cylinder is not None:
        return trimesh.creation.cylinder(radius=geometry.cylinder.radius, height=geometry.cylinder.length)
    if geometry.sphere is not None:
        return trimesh.creation.icosphere(subdivisions=1, radius=geometry.sphere.radius)
    return None


def _colour(visual, materials):
    material = visual.material
    if material is not None and material.color is None and material.name in materials:
        material = materials[material.name]
    if material is None or material.color is None:
        return DEFAULT_COLOUR
    return tuple(float(c) for c in material.color.rgba[:3])


@functools.lru_cache(maxsize=8)
def _link_meshes(source, resolution):
    """{link: (vertices (nv, 3) [m] in the link frame, faces (nf, 3), RGB)} of a URDF path, or
    of the assembled iRonCub when source is None."""
    if source is None:
        urdf, folder = assemble_urdf(ironcub_description()), None
    else:
        urdf, folder = read_urdf(source), pathlib.Path(source).resolve().parent
    materials = {m.name: m for m in urdf.robot.materials}
    meshes = {}
    for link in urdf.robot.links:
        parts = []
        for visual in link.visuals:
            mesh = _geometry(visual.geometry, folder)
            if mesh is None:
                continue
            origin = visual.origin if visual.origin is not None else np.eye(4)
            vertices = np.asarray(mesh.vertices) @ origin[:3, :3].T + origin[:3, 3]
            vertices, faces = cluster_vertices(vertices, np.asarray(mesh.faces), resolution)
            parts.append((vertices, faces, _colour(visual, materials)))
        if parts:
            meshes[link.name] = parts
    return meshes


def load_robot_mesh(robot, urdf=None, resolution=RESOLUTION):
    """The ``RobotMesh`` of a ``Robot`` from the visuals of its URDF.

    urdf: path of the robot's URDF; None reads the assembled default iRonCub (only valid for
    that robot). Links the model does not know are skipped. Raises MeshNotFoundError when a
    mesh file is missing or unreadable, and ValueError when there is no URDF to read.
    """
    if urdf is None and robot.name != ironcub_description()["name"]:
        raise ValueError(f"robot {robot.name!r} is not the default iRonCub: pass urdf= (its URDF path) to draw its meshes")
    model = robot.model
    vertices, bodies, faces, colours, offset = [], [], [], [], 0
    for link, parts in _link_meshes(None if urdf is None else str(urdf), float(resolution)).items():
        if link not in model.frame_names:
            continue
        frame = model.frame_index(link)
        R, p = np.asarray(model.frame_rotation[frame]), np.asarray(model.frame_translation[frame])
        for link_vertices, link_faces, colour in parts:
            vertices.append(link_vertices @ R.T + p)
            bodies.append(np.full(len(link_vertices), model.topology.frame_body[frame]))
            faces.append(link_faces + offset)
            colours.append(np.tile(colour, (len(link_faces), 1)))
            offset += len(link_vertices)
    if not vertices:
        raise MeshNotFoundError(f"the URDF of robot {robot.name!r} has no visual meshes")
    return RobotMesh(np.concatenate(vertices), np.concatenate(bodies), np.concatenate(faces), np.concatenate(colours))
