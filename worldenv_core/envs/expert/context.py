"""Privileged read access to a LIBERO simulation for scripted experts.

The expert is *privileged*: it reads ground-truth poses straight from MuJoCo instead of
perceiving them.  Everything here is read-only; stepping the env is the caller's job (the
motion generators yield actions, the caller steps the env, and on resumption the generators
read fresh state through this context).

Conventions (robosuite 1.4 / LIBERO):
* positions are world-frame metres; the table top is at z ~= 0.90 in tabletop scenes;
* quaternions returned here are **xyzw** (robosuite's convention, not MuJoCo's wxyz);
* "names" are the BDDL names: objects/fixtures (``plate_1``) or regions/sites
  (``basket_1_contain_region``, ``main_table_plate_region``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import robosuite.utils.transform_utils as T

# Gripper pointing straight down with yaw 0: the orientation the Panda starts in for LIBERO
# (eef quat xyzw ~ (1, 0, 0, 0), i.e. a 180 deg turn about world x).
TOP_DOWN = np.diag([1.0, -1.0, -1.0])


def yaw_matrix(yaw: float) -> np.ndarray:
    """Rotation about world z by ``yaw`` radians."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def top_down_mat(yaw: float) -> np.ndarray:
    """Gripper orientation pointing down, turned by ``yaw`` about world z."""
    return yaw_matrix(yaw) @ TOP_DOWN


def wrap_angle(a: float) -> float:
    """Wrap an angle to [-pi, pi)."""
    return float((a + np.pi) % (2 * np.pi) - np.pi)


def wrap_half_pi(a: float) -> float:
    """Wrap to [-pi/2, pi/2): a parallel gripper is symmetric under a half turn."""
    return float((a + np.pi / 2) % np.pi - np.pi / 2)


@dataclass
class ExpertContext:
    """Everything a primitive needs: the env (read-only access) and a random generator.

    ``env`` may be the ``OffScreenRenderEnv``/``ControlEnv`` wrapper or the inner robosuite
    env; ``self.sim_env`` always resolves to the inner one (which owns ``sim``,
    ``objects_dict``, ``object_sites_dict`` ...).
    """

    env: object
    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))

    # ------------------------------------------------------------------ handles
    @property
    def sim_env(self):
        return getattr(self.env, "env", self.env)

    @property
    def sim(self):
        return self.sim_env.sim

    @property
    def model(self):
        return self.sim.model

    @property
    def data(self):
        return self.sim.data

    @property
    def robot(self):
        return self.sim_env.robots[0]

    @property
    def goal_state(self) -> list:
        return self.sim_env.parsed_problem["goal_state"]

    # ------------------------------------------------------------------ end effector
    def eef_pos(self) -> np.ndarray:
        """Grip-site position (between the fingertips), world frame."""
        return np.array(self.data.site_xpos[self.robot.eef_site_id])

    def eef_mat(self) -> np.ndarray:
        return np.array(self.data.site_xmat[self.robot.eef_site_id]).reshape(3, 3)

    def eef_quat(self) -> np.ndarray:
        """xyzw."""
        return T.mat2quat(self.eef_mat())

    def eef_yaw(self) -> float:
        """Yaw of the gripper about world z, relative to :data:`TOP_DOWN`."""
        m = self.eef_mat() @ TOP_DOWN.T  # == yaw_matrix(yaw) when pointing down
        return float(np.arctan2(m[1, 0], m[0, 0]))

    def finger_qpos(self) -> np.ndarray:
        return np.array([self.data.qpos[i] for i in self.robot._ref_gripper_joint_pos_indexes])

    def gripper_opening(self) -> float:
        """Distance between the two finger joints (m); ~0.08 fully open, ~0 closed empty."""
        q = self.finger_qpos()
        return float(abs(q[0] - q[1]))

    def finger_axis(self) -> np.ndarray:
        """World unit vector along which the fingers close (left pad -> right pad)."""
        g = self.robot.gripper
        l = self.geom_pos(g.important_geoms["left_fingerpad"][0])
        r = self.geom_pos(g.important_geoms["right_fingerpad"][0])
        v = r - l
        return v / (np.linalg.norm(v) + 1e-9)

    # ------------------------------------------------------------------ names -> poses
    def is_site(self, name: str) -> bool:
        return name in self.sim_env.object_sites_dict

    def is_object(self, name: str) -> bool:
        return name in self.sim_env.obj_body_id

    def body_id(self, name: str) -> int:
        return self.sim_env.obj_body_id[name]

    def body_pos_raw(self, body_name: str) -> np.ndarray:
        return np.array(self.data.body_xpos[self.model.body_name2id(body_name)])

    def geom_pos(self, geom_name: str) -> np.ndarray:
        return np.array(self.data.geom_xpos[self.model.geom_name2id(geom_name)])

    def pos(self, name: str) -> np.ndarray:
        """Position of an object/fixture root body, or of a region site."""
        if self.is_site(name):
            return np.array(self.data.get_site_xpos(name))
        return np.array(self.data.body_xpos[self.body_id(name)])

    def mat(self, name: str) -> np.ndarray:
        if self.is_site(name):
            return np.array(self.data.get_site_xmat(name)).reshape(3, 3)
        return np.array(self.data.body_xmat[self.body_id(name)]).reshape(3, 3)

    def quat(self, name: str) -> np.ndarray:
        """xyzw."""
        return T.mat2quat(self.mat(name))

    def yaw(self, name: str) -> float:
        """Heading of the object's local x axis projected on the table plane."""
        m = self.mat(name)
        return float(np.arctan2(m[1, 0], m[0, 0]))

    def site_size(self, name: str) -> np.ndarray:
        """Half-extents of a region site (as LIBERO's ``in_box`` uses them)."""
        return np.asarray(self.sim_env.object_sites_dict[name].size, dtype=float)

    def site_parent(self, name: str) -> str | None:
        return self.sim_env.object_sites_dict[name].parent_name

    def get_object(self, name: str):
        return self.sim_env.get_object(name)

    def category(self, name: str) -> str:
        """LIBERO category name (``akita_black_bowl``, ``basket``, ``target_zone``...)."""
        obj = self.get_object(name)
        cat = getattr(obj, "category_name", None)
        return cat if cat else type(obj).__name__.lower()

    # ------------------------------------------------------------------ geometry
    @cached_property
    def _body_subtrees(self) -> dict:
        """body id -> all descendant body ids (incl. itself); static, so cached."""
        parent = self.model.body_parentid
        out: dict[int, list[int]] = {}
        for b in range(self.model.nbody):
            a = b
            while True:
                out.setdefault(a, []).append(b)
                if a == 0:
                    break
                a = parent[a]
        return out

    def geom_ids(self, name: str, collision_only: bool = True) -> list[int]:
        """Geoms of an object's body subtree (collision geoms: contype/conaffinity != 0)."""
        bodies = set(self._body_subtrees[self.body_id(name)])
        ids = [g for g in range(self.model.ngeom) if self.model.geom_bodyid[g] in bodies]
        if collision_only:
            coll = [
                g for g in ids
                if self.model.geom_contype[g] != 0 or self.model.geom_conaffinity[g] != 0
            ]
            ids = coll or ids
        return ids

    def geom_corners(self, name: str, collision_only: bool = True) -> np.ndarray:
        """World-frame corners (N*8, 3) of the local AABBs of the object's geoms."""
        pts = []
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
        for g in self.geom_ids(name, collision_only):
            c, h = self.model.geom_aabb[g][:3], self.model.geom_aabb[g][3:]
            local = c + signs * h
            R = self.data.geom_xmat[g].reshape(3, 3)
            pts.append(self.data.geom_xpos[g] + local @ R.T)
        return np.concatenate(pts, axis=0)

    def aabb(self, name: str, collision_only: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """World axis-aligned bounding box (lo, hi) of an object; for a site, its box."""
        if self.is_site(name):
            c, h = self.pos(name), np.abs(self.mat(name) @ self.site_size(name))
            return c - h, c + h
        p = self.geom_corners(name, collision_only)
        return p.min(0), p.max(0)

    def footprint(self, name: str) -> tuple[np.ndarray, np.ndarray, float]:
        """Oriented table-plane footprint: (centre_xy, half_extents_xy, yaw).

        Computed in the object's own yaw frame, so for a rotated box the extents are the
        box's real length/width (what a side grasp must straddle).
        """
        yaw = self.yaw(name)
        Rz = yaw_matrix(yaw)[:2, :2]
        p = self.geom_corners(name)[:, :2] @ Rz  # into the object frame
        lo, hi = p.min(0), p.max(0)
        centre = Rz @ ((lo + hi) / 2)
        return centre, (hi - lo) / 2, yaw

    def top_z(self, name: str) -> float:
        return float(self.aabb(name)[1][2])

    def bottom_z(self, name: str) -> float:
        return float(self.aabb(name)[0][2])

    def max_object_speed(self) -> float:
        """Largest linear speed (m/s) among the scene's movable objects.

        Some init states place objects slightly above their support (e.g. a bowl in a
        drawer); they fall during the first steps, and geometry read before that is stale.
        """
        v = 0.0
        for name in self.sim_env.objects_dict:
            bid = self.body_id(name)
            # cvel is (rot, lin) in the body's com frame; the lin part is enough here
            v = max(v, float(np.linalg.norm(self.data.cvel[bid][3:])))
        return v

    # ------------------------------------------------------------------ contacts
    def _geom_set(self, name: str) -> set[int]:
        return set(self.geom_ids(name, collision_only=False))

    def in_contact(self, name_a: str, name_b: str) -> bool:
        a, b = self._geom_set(name_a), self._geom_set(name_b)
        for i in range(self.data.ncon):
            c = self.data.contact[i]
            if (c.geom1 in a and c.geom2 in b) or (c.geom1 in b and c.geom2 in a):
                return True
        return False

    def finger_contacts(self, name: str) -> tuple[bool, bool]:
        """(left finger touches object, right finger touches object)."""
        g = self.robot.gripper
        obj = self._geom_set(name)
        sides = []
        for key in ("left_finger", "right_finger"):
            fid = {self.model.geom_name2id(n) for n in g.important_geoms[key]}
            hit = False
            for i in range(self.data.ncon):
                c = self.data.contact[i]
                if (c.geom1 in fid and c.geom2 in obj) or (c.geom2 in fid and c.geom1 in obj):
                    hit = True
                    break
            sides.append(hit)
        return sides[0], sides[1]

    def is_grasped(self, name: str) -> bool:
        """Both fingers touch the object (robosuite's own grasp test)."""
        l, r = self.finger_contacts(name)
        return l and r

    def is_holding(self, name: str) -> bool:
        """Looser than :meth:`is_grasped`: a finger touches it and the fingers are not shut.

        A rim grasp tilts the object and one finger pad can lose contact for a step while
        lifting even though the object comes along.
        """
        l, r = self.finger_contacts(name)
        return (l or r) and self.gripper_opening() > 0.003

    def check_predicate(self, pred: list) -> bool:
        """Evaluate one BDDL goal predicate with LIBERO's own checker."""
        return bool(self.sim_env._eval_predicate(pred))
