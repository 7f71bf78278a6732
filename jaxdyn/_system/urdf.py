"""Robots from URDF files, as a `RigidBodyTree` whose masses and inertias are parameters.

Parsed with yourdfpy (install jaxdyn[urdf]); meshes are not loaded. URDF describes a tree by
construction (every link has one parent joint): a file in which a link is the child of two
joints — a closed loop — is refused with an error; loop closures are constraints, not joints.
Mimic joints are imported as independent joints (as Pinocchio does by default).
"""

from typing import Any

import numpy as np

from .._state import transferred
from .joints import Fixed, Free, Planar, Prismatic, Revolute
from .links import Link, LinkParameter
from .tree import RigidBodyTree


def from_urdf(path, *, floating: bool = False, gravity=(0.0, 0.0, -9.81),
              parameters: bool = True, damping: bool = True, locked=()):
    """Load a URDF robot model.

    **Arguments:**

    - `path`: the .urdf file.
    - `floating`: if True the root link moves freely (a `Free` joint: 6 degrees of freedom,
      q = (position, quaternion (w, x, y, z)), u = (v, ω) in the root link's axes), as for
      legged robots and humanoids; else it is fixed to the world.
    - `gravity`: the gravitational acceleration in world axes (URDF's z is up).
    - `parameters`: if True (the default) every link's mass, centre of mass and inertia are
      read from the parameters p, so that they can be fitted, and the values in the file are
      returned as p; if False they are constants of the tree and p is None.
    - `damping`: if True (the default) a joint's viscous damping `<dynamics damping="c">`
      becomes a damper −c q̇ on it (a parameter "damping" of the link it moves, with
      `parameters`); Coulomb `friction` is not imported (it is not smooth). Pinocchio's
      `aba` ignores both: compare with it using `damping=False`.
    - `locked`: names of joints welded at their zero position (`Fixed`), e.g. a gripper's
      fingers when planning the arm's motion (Pinocchio's `buildReducedModel` with a zero
      reference configuration).

    **Returns:** (tree, p), with p = {link name: {"mass", "com", "inertia"[, "damping"]}}
    (inertia about the centre of mass, in link axes).

    Joints: revolute and continuous → `Revolute` (an angle), prismatic → `Prismatic`, fixed →
    `Fixed`, floating → `Free`, planar (about the joint's z axis) → `Planar`.
    """
    model, _ = _load(path)
    links = {link.name: link for link in model.links}
    parent_joint = {}
    for joint in model.joints:
        if joint.child in parent_joint:
            raise ValueError(
                f"Link {joint.child!r} is the child of two joints "
                f"({parent_joint[joint.child].name!r} "
                f"and {joint.name!r}): the file describes a closed loop, which a tree of joints "
                "cannot express. Import the tree without one of them and close the loop with a "
                "constraint."
            )
        if joint.parent not in links or joint.child not in links:
            raise ValueError(f"Joint {joint.name!r} connects links that are not in the file.")
        parent_joint[joint.child] = joint
    unknown = set(locked) - {joint.name for joint in model.joints}
    if unknown:
        raise ValueError(f"locked names joints that are not in the file: {sorted(unknown)}.")
    roots = [name for name in links if name not in parent_joint]
    if len(roots) != 1:
        raise ValueError(f"A URDF tree has one root link, this file has {roots}.")
    children = {name: [] for name in links}
    for joint in model.joints:  # in file order, as parsers of URDF list them
        children[joint.parent].append(joint.child)

    tree_links, values = [], {}
    stack = [roots[0]]
    while stack:  # depth first: parents before children
        name = stack.pop()
        stack.extend(reversed(children[name]))
        mass, com, inertia = _inertial(links[name])
        values[name] = {"mass": mass, "com": com, "inertia": inertia}
        if name == roots[0]:
            joint, translation, rotation, parent = (Free() if floating else Fixed()), \
                np.zeros(3), np.eye(3), None
        else:
            urdf_joint = parent_joint[name]
            joint = Fixed() if urdf_joint.name in locked else _joint(urdf_joint)
            origin = np.eye(4) if urdf_joint.origin is None else np.asarray(urdf_joint.origin)
            translation, rotation, parent = origin[:3, 3], origin[:3, :3], urdf_joint.parent
            dynamics = urdf_joint.dynamics
            if damping and joint.nv == 1 and dynamics is not None and dynamics.damping:
                values[name]["damping"] = np.asarray(float(dynamics.damping))
        # Link's keyword arguments: mass, com, inertia (and damping) as values or parameters.
        inertial: dict[str, Any] = {k: LinkParameter(name, k) if parameters else v
                                    for k, v in values[name].items()}
        if not parameters:
            inertial.update(com=tuple(com), inertia=transferred(inertia))
        tree_links.append(Link(name, joint, parent=parent, translation=translation,
                               rotation=rotation, **inertial))
    p = {name: {k: transferred(v) for k, v in d.items()} for name, d in values.items()}
    tree = RigidBodyTree(tree_links, gravity=transferred(gravity, float))
    return tree, (p if parameters else None)


def _load(path):
    """(yourdfpy's robot, {(link, index of its collision): (radius, length)} of its capsules).

    URDF has no capsule; files written for Drake or sdformat carry `<capsule radius length>`,
    which yourdfpy refuses. They are read here and handed to it as cylinders (which
    `from_urdf` does not use), so that such files load."""
    import io
    import xml.etree.ElementTree as ElementTree

    try:
        import yourdfpy
    except ImportError as error:  # an optional dependency
        raise ImportError("URDF import needs yourdfpy: pip install 'jaxdyn[urdf]'.") from error
    root = ElementTree.parse(str(path)).getroot()
    capsules = {}
    for link in root.iter("link"):
        for k, collision in enumerate(link.findall("collision")):
            geometry = collision.find("geometry")
            capsule = None if geometry is None else geometry.find("capsule")
            if capsule is not None:
                radius, length = capsule.get("radius"), capsule.get("length")
                if radius is None or length is None:
                    raise ValueError(f"A <capsule> of link {link.get('name')!r} lacks its "
                                     "radius or length attribute.")
                capsules[link.get("name"), k] = (float(radius), float(length))
                capsule.tag = "cylinder"
    file = io.BytesIO(ElementTree.tostring(root))
    model = yourdfpy.URDF.load(file, load_meshes=False, build_scene_graph=False,
                               build_collision_scene_graph=False,
                               load_collision_meshes=False).robot
    return model, capsules


def _inertial(link):
    inertial = link.inertial
    if inertial is None or inertial.mass is None:
        return np.asarray(0.0), np.zeros(3), np.zeros((3, 3))
    origin = np.eye(4) if inertial.origin is None else np.asarray(inertial.origin)
    rotation = origin[:3, :3]
    inertia = np.zeros((3, 3)) if inertial.inertia is None else np.asarray(inertial.inertia)
    # URDF gives the inertia in the frame of <inertial><origin>; jaxdyn in the link's axes.
    return np.asarray(float(inertial.mass)), origin[:3, 3].copy(), rotation @ inertia @ rotation.T


def _joint(joint):
    axis = np.array([1.0, 0.0, 0.0]) if joint.axis is None else np.asarray(joint.axis, float)
    if joint.type in ("revolute", "continuous"):
        return Revolute(axis)
    if joint.type == "prismatic":
        return Prismatic(axis)
    if joint.type == "fixed":
        return Fixed()
    if joint.type == "floating":
        return Free()
    if joint.type == "planar":
        if not np.allclose(axis / np.linalg.norm(axis), [0.0, 0.0, 1.0]):
            raise ValueError(f"Planar joint {joint.name!r}: only planes normal to the joint's z "
                             "axis are supported; rotate the joint's origin instead.")
        return Planar()
    raise ValueError(f"Joint {joint.name!r} has the unknown type {joint.type!r}.")


def example_robot_urdf(name: str) -> str:
    """The path of a robot model of the example-robot-data collection (`pip install
    example-robot-data`, which installs its files under site-packages), for `from_urdf`.

    `name` is a URDF file's name without ".urdf" ("panda", "ur5_robot", "talos_full_v2",
    "g1_29dof_rev_1_0"), its robot's name where that robot has one file ("anymal_c" for
    anymal_c_simple_description/urdf/anymal.urdf, "go2"), a unique prefix of a file's name
    ("ur5" finds ur5_robot.urdf first, "solo12"), or the end of its path
    ("anymal_c_simple_description/urdf/anymal.urdf") where names repeat. An unknown or
    ambiguous name is an error that lists names which each find one file.
    """
    import importlib.metadata

    try:
        files = [f for f in importlib.metadata.files("example-robot-data") or []
                 if str(f).endswith(".urdf")]
    except importlib.metadata.PackageNotFoundError:
        raise ValueError("example-robot-data is not installed: pip install example-robot-data "
                         "(or jaxdyn[test]).") from None
    found = _find_example_robot(name, files)
    if isinstance(found, list):
        listed = ", ".join(_shortest_names(found, files))
        if found:
            raise ValueError(f"{name!r} names several example robots: {listed}. Pass one of "
                             "these names.")
        raise ValueError(f"No example robot is named {name!r}; the collection has: "
                         f"{', '.join(_shortest_names(files, files))}.")
    return str(found.locate())


def _stem(f):
    return str(f).rsplit("/", 1)[-1][:-len(".urdf")]


def _robot(f):
    """The robot a file of example-robot-data describes: its folder's name up to
    "_description" or "_data" (anymal_c_simple_description → "anymal_c_simple", and
    "anymal_c" by prefix)."""
    folder = str(f).split("example-robot-data/robots/")[-1].split("/", 1)[0]
    return folder.rsplit("_description", 1)[0].rsplit("_data", 1)[0]


def _find_example_robot(name, files):
    """The one file that `name` finds, or the list of candidates (empty: none)."""
    for candidates in ([f for f in files if str(f).endswith("/" + name)],
                       [f for f in files if _stem(f) == name],
                       [f for f in files if _stem(f) == name + "_robot"]):
        if candidates:
            return candidates[0] if len(candidates) == 1 else candidates
    by_robot = [f for f in files if _robot(f) == name or _robot(f).startswith(name + "_")]
    if len(by_robot) == 1:
        return by_robot[0]
    candidates = [f for f in files if _stem(f).startswith(name)]
    if len(candidates) == 1:
        return candidates[0]
    return candidates or by_robot


def _shortest_names(chosen, files):
    """For each file of `chosen`, the shortest name that finds it alone: its name without
    ".urdf" where that is unique, else the end of its path."""
    names = []
    for f in chosen:
        relative = str(f).split("example-robot-data/robots/")[-1]
        names.append(_stem(f) if _find_example_robot(_stem(f), files) is f else relative)
    return sorted(names)


def urdf_contact_points(path, links=None) -> list:
    """Contact points from a URDF file's collision geometry, for `jaxdyn.Contact`:
    a sphere → a `ContactPoint` of its radius at its centre; a capsule (`<capsule radius
    length>`, an extension of URDF that Drake and sdformat read) → the spheres at the ends of
    its axis (`jaxdyn.capsule_ends`); a box → its eight corners. Cylinders and meshes are not
    taken (give their points yourself, e.g. `jaxdyn.box_corners` for a body's bounding box).

    **Arguments:** `path`, the .urdf file; `links`, the names of the links whose geometry to
    take (default every link), e.g. a legged robot's feet.

    **Example:** ANYmal-C's feet, spheres of 3 cm at the ends of its shanks:

        feet = jaxdyn.urdf_contact_points(path, links=["LF_FOOT", "RF_FOOT", "LH_FOOT", "RH_FOOT"])
    """
    from .contact import ContactPoint, box_corners, capsule_ends

    model, capsules = _load(path)
    names = [link.name for link in model.links]
    for name in links or ():
        if name not in names:
            raise ValueError(f"The URDF file has no link named {name!r}.")
    points = []
    for link in model.links:
        if links is not None and link.name not in links:
            continue
        for k, collision in enumerate(link.collisions):
            origin = np.eye(4) if collision.origin is None else np.asarray(collision.origin)
            rotation, centre = origin[:3, :3], origin[:3, 3]
            geometry = collision.geometry
            if geometry.sphere is not None:
                points.append(ContactPoint(link.name, centre, float(geometry.sphere.radius),
                                           name=link.name))
            elif geometry.box is not None:
                points += box_corners(link.name, geometry.box.size, centre, rotation)
            elif (link.name, k) in capsules:
                points += capsule_ends(link.name, *capsules[link.name, k], centre, rotation)
    if links is not None and not points:
        raise ValueError(f"The links {list(links)} have no collision spheres, capsules or "
                         "boxes in the URDF file: give their contact points yourself.")
    return points
