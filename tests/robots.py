"""Robot models of the example-robot-data package in jaxdyn and in Pinocchio, with random states
in both conventions: the independent reference for trees of joints.

Pinocchio numbers its joints (each a block of q and v) and stores a free-flyer quaternion as
(x, y, z, w); jaxdyn numbers its links (fixed joints included) and stores (w, x, y, z). A
`Robot` maps between them; `permutation` P takes jaxdyn's speeds to Pinocchio's (v_pin = P u).
"""

import dataclasses
import importlib.metadata

import numpy as np
import pinocchio as pin
import yourdfpy

import jaxdyn


def robot_file(name):
    """A URDF of the example-robot-data package (installed with the test extras)."""
    for f in importlib.metadata.files("example-robot-data"):
        if str(f).endswith("/" + name):
            return str(f.locate())
    raise FileNotFoundError(name)


@dataclasses.dataclass
class Robot:
    path: str
    floating: bool
    tree: jaxdyn.RigidBodyTree
    p: dict
    model: object
    data: object
    joint_link: dict  # Pinocchio joint index → the jaxdyn link it moves
    permutation: np.ndarray

    @classmethod
    def load(cls, path, floating=False):
        tree, p = jaxdyn.from_urdf(path, floating=floating, damping=False)  # Pinocchio has none
        model = (pin.buildModelFromUrdf(path, pin.JointModelFreeFlyer()) if floating
                 else pin.buildModelFromUrdf(path))
        robot = yourdfpy.URDF.load(path, load_meshes=False, build_scene_graph=False,
                                   build_collision_scene_graph=False,
                                   load_collision_meshes=False).robot
        child = {joint.name: joint.child for joint in robot.joints}
        joint_link = {j: tree.links[0].name if model.names[j] == "root_joint"
                      else child[model.names[j]] for j in range(1, model.njoints)}
        u_slices = tree.speed_slices()
        permutation = np.zeros((model.nv, model.nv))
        for j, link in joint_link.items():
            iv, nv = model.idx_vs[j], model.nvs[j]
            permutation[iv:iv + nv, u_slices[link]] = np.eye(nv)
        return cls(path, floating, tree, p, model, model.createData(), joint_link, permutation)

    def coordinates(self, q_pin):
        """jaxdyn's q from Pinocchio's."""
        q = np.zeros(self.tree.num_coordinates)
        q_slices = self.tree.coordinate_slices()
        for j, link in self.joint_link.items():
            iq, nq = self.model.idx_qs[j], self.model.nqs[j]
            q_joint = q_pin[iq:iq + nq]
            if self.model.names[j] == "root_joint":  # (x, y, z, w) → (w, x, y, z)
                q_joint = np.concatenate([q_joint[:3], q_joint[6:], q_joint[3:6]])
            q[q_slices[link]] = q_joint
        return q

    def random_states(self, num_states, seed=0):
        """(q_pin, v_pin, a_pin) and jaxdyn's (q, u, u̇), stacked."""
        rng = np.random.default_rng(seed)
        q_pin = np.stack([pin.randomConfiguration(self.model, -np.ones(self.model.nq),
                                                  np.ones(self.model.nq))
                          for _ in range(num_states)])
        v_pin, a_pin = (rng.normal(size=(num_states, self.model.nv)) for _ in range(2))
        q = np.stack([self.coordinates(x) for x in q_pin])
        to_jaxdyn = self.permutation.T
        return (q_pin, v_pin, a_pin), (q, v_pin @ to_jaxdyn.T, a_pin @ to_jaxdyn.T)
