"""Builds the MJCF model of the ADL scene for one task and one randomised scene specification."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .person import ELBOW, FOREARM_BODY, HAND, HEAD_BODY, NECK, pivot_in_base

# Fixed geometry (metres, base_link frame).
TABLE_TOP_Z = 0.0
SHOULDER_Z = 0.32
HAND_DOWN_QUAT = (0.0, 1.0, 0.0, 0.0)  # hand z-axis pointing down (180 deg about x), as a wxyz quaternion
MARKER_GROUP = 5
DUSTPAN_HALF = (0.07, 0.05)
HOME_TCP = np.array([0.0, 0.22, 0.22])
CAMERA_POS = np.array([0.80, -0.40, 0.95])
CAMERA_LOOKAT = np.array([0.0, 0.30, 0.22])
ARM_JOINTS = [f"joint{i}" for i in range(1, 8)]
FINGER_JOINTS = ["finger_left", "finger_right"]
HOME_Q = np.array([0.0, -0.45, 0.0, -1.75, 0.0, -0.95, 0.0])  # tcp above the table, hand pointing down


@dataclass
class SceneSpec:
    """Everything needed to rebuild an episode's initial scene (stored in the bag as tf of the objects).

    poses: object name -> (x, y, z, yaw) of its body frame in base_link; "manikin" included.
    """

    task: str
    poses: dict[str, tuple[float, float, float, float]]
    tool: str | None = None
    extras: dict[str, float] = field(default_factory=dict)
    person: dict[str, float] = field(default_factory=dict)  # the person's motion (adlpipe.sim.person); {}: still


def _camera_xyaxes(pos: np.ndarray, lookat: np.ndarray) -> str:
    fwd = lookat - pos
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    return " ".join(f"{v:.6f}" for v in (*right, *up))


def _yaw_quat(yaw: float) -> str:
    return f"{np.cos(yaw / 2):.6f} 0 0 {np.sin(yaw / 2):.6f}"


def _arm_xml(tool_xml: str) -> str:
    """A 7-DoF anthropomorphic arm (yaw, pitch, roll, elbow, roll, wrist pitch, roll) with a parallel gripper."""
    # The arm, hand and tools collide with the manikin only (ROBOT_CONTACT vs MANIKIN_AFFINITY): touching the
    # person is a real contact with a measurable force; the table and objects stay out of the arm's way.
    link = f'rgba="0.85 0.85 0.9 1" {ROBOT_CONTACT}'
    return f"""
    <body name="arm_base" pos="0 0 0" gravcomp="1">
      <geom type="cylinder" size="0.07 0.03" pos="0 0 0.03" {link}/>
      <body name="link1" pos="0 0 0.06" gravcomp="1">
        <joint name="joint1" axis="0 0 1" range="-2.9 2.9"/>
        <geom type="capsule" fromto="0 0 0 0 0 0.26" size="0.045" {link}/>
        <body name="link2" pos="0 0 0.26" gravcomp="1">
          <joint name="joint2" axis="1 0 0" range="-2.0 2.0"/>
          <geom type="sphere" size="0.05" {link}/>
          <body name="link3" pos="0 0 0" gravcomp="1">
            <joint name="joint3" axis="0 0 1" range="-2.9 2.9"/>
            <geom type="capsule" fromto="0 0 0 0 0 0.45" size="0.04" {link}/>
            <body name="link4" pos="0 0 0.45" gravcomp="1">
              <joint name="joint4" axis="1 0 0" range="-2.8 0.1"/>
              <geom type="sphere" size="0.042" {link}/>
              <body name="link5" pos="0 0 0" gravcomp="1">
                <joint name="joint5" axis="0 0 1" range="-2.9 2.9"/>
                <geom type="capsule" fromto="0 0 0 0 0 0.42" size="0.035" {link}/>
                <body name="link6" pos="0 0 0.42" gravcomp="1">
                  <joint name="joint6" axis="1 0 0" range="-2.2 2.2"/>
                  <geom type="sphere" size="0.036" {link}/>
                  <body name="hand" pos="0 0 0" gravcomp="1">
                    <joint name="joint7" axis="0 0 1" range="-2.9 2.9"/>
                    <geom type="box" size="0.05 0.025 0.02" pos="0 0 0.05" rgba="0.3 0.3 0.35 1"
                          {ROBOT_CONTACT}/>
                    <body name="finger_l" pos="0 0 0.09" gravcomp="1">
                      <joint name="finger_left" type="slide" axis="1 0 0" range="0 0.04"/>
                      <geom type="box" size="0.006 0.012 0.025" pos="0.006 0 0" rgba="0.2 0.2 0.2 1"
                            {ROBOT_CONTACT}/>
                    </body>
                    <body name="finger_r" pos="0 0 0.09" gravcomp="1">
                      <joint name="finger_right" type="slide" axis="-1 0 0" range="0 0.04"/>
                      <geom type="box" size="0.006 0.012 0.025" pos="-0.006 0 0" rgba="0.2 0.2 0.2 1"
                            {ROBOT_CONTACT}/>
                    </body>
                    <site name="tcp" pos="0 0 0.11" size="0.006" rgba="1 0 0 0.6"/>
                    {tool_xml}
                  </body>
                </body>
              </body>
            </body>
          </body>
        </body>
      </body>
    </body>"""


# Tools held rigidly in the hand for the contact tasks; each ends in a `tool_tip` site. The sponge, comb and broom
# tips are TOOL_LENGTH below the tcp; the spoon and toothbrush are L-shaped (a vertical handle, then a head
# reaching TOOL_REACH towards the manikin) so that the handle stays clear of the face.
TOOL_LENGTH = 0.07
TOOL_REACH = 0.035
ROBOT_CONTACT = 'contype="2" conaffinity="0"'  # collides with geoms whose conaffinity has bit 2: the manikin only
# The manikin collides with objects (bit 1) and the robot (bit 2). Its skin is soft (a long contact time constant,
# and solmix so that its parameters win over the tool's): pressing a tool a few mm in costs a few newtons, as on a
# person, instead of the tens of newtons of a rigid contact against the stiff position-controlled arm.
MANIKIN_CONTACT = 'contype="1" conaffinity="3" solref="0.08 1" solimp="0.5 0.95 0.02" solmix="100"'

_TOOLS = {
    "broom": '<geom type="box" size="0.06 0.01 0.02" pos="0 0 {tip_c}" rgba="0.6 0.4 0.2 1" mass="0.05" '
    'friction="0.8 0.01 0.001" contype="3" conaffinity="1"/>',
    "sponge": '<geom type="box" size="0.025 0.02 0.015" pos="0 0 {tip_c}" rgba="1 0.9 0.2 1" {robot}/>',
    "spoon": '<geom type="capsule" fromto="0 0 0.09 0 0 {tip}" size="0.006" rgba="0.8 0.8 0.8 1" {robot}/>'
    '<geom type="capsule" fromto="0 0 {tip} 0 {reach} {tip}" size="0.006" rgba="0.8 0.8 0.8 1" {robot}/>',
    "comb": '<geom type="box" size="0.04 0.004 0.02" pos="0 0 {tip_c}" rgba="0.1 0.1 0.1 1" {robot}/>',
    "toothbrush": '<geom type="capsule" fromto="0 0 0.09 0 0 {tip}" size="0.005" rgba="0.2 0.6 1 1" {robot}/>'
    '<geom type="capsule" fromto="0 0 {tip} 0 {reach} {tip}" size="0.005" rgba="0.2 0.6 1 1" {robot}/>',
}
L_SHAPED = {"spoon", "toothbrush"}


def tool_tip_offset(tool: str | None) -> np.ndarray:
    """Where a held tool's tip is relative to the tcp, in base_link (the hand points down, its y along -y)."""
    if tool is None:
        return np.zeros(3)
    return np.array([0.0, TOOL_REACH if tool in L_SHAPED else 0.0, -TOOL_LENGTH])


def _tool_xml(tool: str | None) -> str:
    if tool is None:
        return ""
    tip = 0.11 + TOOL_LENGTH
    reach = -TOOL_REACH if tool in L_SHAPED else 0.0  # hand y is world -y
    geom = _TOOLS[tool].format(tip=f"{tip:.3f}", tip_c=f"{tip - 0.015:.3f}", reach=f"{reach:.3f}",
                               robot=ROBOT_CONTACT)
    return (f'<body name="tool" pos="0 0 0">{geom}<site name="tool_tip" pos="0 {reach:.3f} {tip:.3f}" '
            'size="0.006"/></body>')


def _xyz(p: np.ndarray) -> str:
    return " ".join(f"{float(c):.6g}" for c in p)


# The manikin's parts in its frame (a seated person facing the robot, -y): geoms and the sites the tasks touch.
# The head (with its sites) and the left forearm are separate parts: bodies of their own for a person who moves
# (adlpipe.sim.person), inline in the manikin for a still one.
_SKIN = 'rgba="0.93 0.78 0.66 1" {contact}'
_HEAD_GEOMS = [
    ('<geom name="head" type="sphere" size="0.085" pos="{}" ' + _SKIN + "/>", [(0, 0.10, 0.40)]),
    ('<geom name="hair" type="sphere" size="0.088" pos="{}" rgba="0.25 0.15 0.08 1" {contact}/>', [(0, 0.115, 0.43)]),
]
_FOREARM_GEOMS = [('<geom type="capsule" fromto="{} {}" size="0.03" ' + _SKIN + "/>", [ELBOW, HAND])]
_HEAD_SITES = {"nose": (0, 0.015, 0.40), "mouth": (0, 0.025, 0.355), "hair_front": (0, 0.06, 0.50),
               "hair_mid": (0, 0.11, 0.518), "hair_back": (0, 0.16, 0.51), "head_top": (0, 0.11, 0.52)}
_FOREARM_SITES = {"forearm_start": (-0.195, 0.005, 0.084), "forearm_end": (-0.135, -0.095, 0.069)}


def _parts(geoms: list, origin: tuple | np.ndarray = (0.0, 0.0, 0.0)) -> str:
    return "".join(xml.format(*(_xyz(np.subtract(p, origin)) for p in pts), contact=MANIKIN_CONTACT)
                   for xml, pts in geoms)


def _sites(sites: dict, origin: tuple | np.ndarray = (0.0, 0.0, 0.0)) -> str:
    return "".join(f'<site name="{n}" pos="{_xyz(np.subtract(p, origin))}" size="0.01" rgba="1 0 0 0.5"/>'
                   for n, p in sites.items())


def _manikin_xml(x: float, y: float, z: float, yaw: float, moving: bool = False) -> str:
    """A seated manikin facing the robot (-y). Sites mark the parts the tasks touch. moving: the head and the left
    forearm as mocap bodies at their pivots (the neck, the elbow), which adlpipe.sim.person moves."""
    skin = f'rgba="0.93 0.78 0.66 1" {MANIKIN_CONTACT}'
    torso = (f'<geom type="box" size="0.17 0.09 0.22" pos="0 0.14 0.05" rgba="0.3 0.45 0.7 1" {MANIKIN_CONTACT}/>'
             f'<geom type="capsule" fromto="0 0.12 0.26 0 0.12 0.32" size="0.04" {skin}/>')
    right = (f'<geom type="capsule" fromto="0.22 0.05 0.06 0.16 -0.10 0.035" size="0.03" {skin}/>'
             f'<geom type="sphere" size="0.035" pos="0.16 -0.12 0.035" {skin}/>')
    hand_rest = _sites({"hand_rest": (0.16, -0.18, 0.04)})
    quat = _yaw_quat(yaw)
    if not moving:
        return (f'<body name="manikin" pos="{x} {y} {z}" quat="{quat}">{torso}{_parts(_HEAD_GEOMS)}'
                f"{_parts(_FOREARM_GEOMS)}{right}{_sites(_HEAD_SITES)}{_sites(_FOREARM_SITES)}{hand_rest}</body>")
    out = f'<body name="manikin" pos="{x} {y} {z}" quat="{quat}">{torso}{right}{hand_rest}</body>'
    for name, pivot, geoms, sites in ((HEAD_BODY, NECK, _HEAD_GEOMS, _HEAD_SITES),
                                      (FOREARM_BODY, ELBOW, _FOREARM_GEOMS, _FOREARM_SITES)):
        at = pivot_in_base((x, y, z, yaw), pivot)
        out += (f'<body name="{name}" mocap="true" pos="{_xyz(at)}" quat="{quat}">{_parts(geoms, pivot)}'
                f"{_sites(sites, pivot)}</body>")
    return out


# Free objects: name -> geoms (body frame at the object's base centre on the table). Graspable objects have a
# `<name>_grasp` site where the gripper takes them.
_OBJECTS = {
    "trash": '<geom type="box" size="0.015 0.015 0.015" pos="0 0 0.015" rgba="0.9 0.2 0.2 1" mass="0.03" '
    'friction="0.6 0.01 0.001"/>',
    "cup": '<geom type="cylinder" size="0.03 0.05" pos="0 0 0.05" rgba="0.5 0.8 1 1" mass="0.15"/>'
    '<site name="cup_grasp" pos="0 0 0.09" size="0.005"/>',
    "towel": '<geom type="box" size="0.06 0.06 0.008" pos="0 0 0.008" rgba="0.95 0.95 0.95 1" mass="0.05"/>'
    '<site name="towel_grasp_l" pos="-0.02 0 0.02" size="0.005"/><site name="towel_grasp_r" pos="0.02 0 0.02" '
    'size="0.005"/>',
    "hat": '<geom type="cylinder" size="0.07 0.008" pos="0 0 0.008" rgba="0.2 0.2 0.25 1" mass="0.06"/>'
    '<geom type="cylinder" size="0.045 0.03" pos="0 0 0.045" rgba="0.2 0.2 0.25 1" mass="0.04"/>'
    '<site name="hat_grasp" pos="0 0 0.085" size="0.005"/>',
    "lid": '<geom type="cylinder" size="0.07 0.006" pos="0 0 0.006" rgba="0.7 0.7 0.75 1" mass="0.06"/>'
    '<geom type="cylinder" size="0.012 0.012" pos="0 0 0.024" rgba="0.4 0.4 0.45 1" mass="0.01"/>'
    '<site name="lid_grasp" pos="0 0 0.04" size="0.005"/>',
}
# Static props: name -> geoms.
_PROPS = {
    "dustpan": f'<geom type="box" size="{DUSTPAN_HALF[0]} {DUSTPAN_HALF[1]} 0.001" pos="0 0 0.001" '
    'rgba="0.2 0.7 0.3 1" contype="0" conaffinity="0"/>',
    "rack": '<geom type="box" size="0.12 0.05 0.004" pos="0 0 0.20" rgba="0.5 0.35 0.2 1"/>'
    '<geom type="cylinder" size="0.01 0.098" pos="0.1 0 0.098" rgba="0.5 0.35 0.2 1"/>'
    '<geom type="cylinder" size="0.01 0.098" pos="-0.1 0 0.098" rgba="0.5 0.35 0.2 1"/>',
    "plate": '<geom type="cylinder" size="0.075 0.006" pos="0 0 0.006" rgba="1 1 1 1"/>'
    '<geom type="sphere" size="0.035" pos="0 0 0.006" rgba="0.8 0.5 0.1 1" contype="0" conaffinity="0"/>',
    "bowl": '<geom type="cylinder" size="0.05 0.025" pos="0 0 0.025" rgba="0.9 0.6 0.3 1"/>',
    "bottle": '<geom type="cylinder" size="0.03 0.09" pos="0 0 0.09" rgba="0.1 0.5 0.2 1"/>',
}
GRASPABLE = set(_OBJECTS) - {"trash"}
SCENE_OBJECTS = set(_OBJECTS) | set(_PROPS) | {"manikin"}  # the frames a scene can be rebuilt from


def build_mjcf(spec: SceneSpec, width: int = 224, height: int = 224, markers: list | None = None) -> str:
    """MJCF text of the scene: camera, lights, table, manikin, the task's objects/props and the arm.

    markers: optional base_link points drawn as small pure-green spheres (no collision, geom group MARKER_GROUP),
    for projection checks.
    """
    bodies = [f'<geom type="sphere" size="0.012" pos="{p[0]} {p[1]} {p[2]}" rgba="0 1 0 1" contype="0" '
              f'conaffinity="0" group="{MARKER_GROUP}"/>' for p in (markers or [])]
    for name, (x, y, z, yaw) in spec.poses.items():
        if name == "manikin":
            bodies.append(_manikin_xml(x, y, z, yaw, moving=bool(spec.person)))
        elif name in _OBJECTS:
            bodies.append(
                f'<body name="{name}" pos="{x} {y} {z}" quat="{_yaw_quat(yaw)}"><freejoint name="{name}_free"/>'
                f"{_OBJECTS[name]}</body>"
            )
        elif name in _PROPS:
            bodies.append(f'<body name="{name}" pos="{x} {y} {z}" quat="{_yaw_quat(yaw)}">{_PROPS[name]}</body>')
        else:
            raise ValueError(f"unknown scene object {name!r}")
    welds = "".join(
        f'<weld name="grasp_{n}" body1="hand" body2="{n}" active="false" solref="0.01 1"/>'
        for n in spec.poses
        if n in GRASPABLE
    )
    actuators = "".join(f'<position joint="{j}" kp="600" kv="40"/>' for j in ARM_JOINTS)
    actuators += "".join(f'<position joint="{j}" kp="200" kv="10" ctrlrange="0 0.04"/>' for j in FINGER_JOINTS)
    xyaxes = _camera_xyaxes(CAMERA_POS.copy(), CAMERA_LOOKAT.copy())
    return f"""<mujoco model="adl_{spec.task.replace(' ', '_')}">
  <compiler angle="radian"/>
  <option timestep="0.002" integrator="implicitfast" cone="elliptic"/>
  <visual><global offwidth="{max(width, 640)}" offheight="{max(height, 480)}" fovy="55"/>
    <quality shadowsize="1024"/><headlight ambient="0.4 0.4 0.4" diffuse="0.5 0.5 0.5"/></visual>
  <default><joint damping="2" armature="0.05"/><geom friction="0.9 0.01 0.001" solref="0.005 1"/></default>
  <worldbody>
    <light pos="0.3 0.2 2.0" dir="0 0 -1" diffuse="0.6 0.6 0.6"/>
    <geom type="plane" size="3 3 0.1" pos="0 0 -0.75" rgba="0.6 0.6 0.55 1"/>
    <geom name="table" type="box" size="0.55 0.42 0.02" pos="0 0.32 -0.02" rgba="0.75 0.6 0.45 1"/>
    <camera name="rgbd" pos="{CAMERA_POS[0]} {CAMERA_POS[1]} {CAMERA_POS[2]}" xyaxes="{xyaxes}" fovy="55"/>
    {''.join(bodies)}
    {_arm_xml(_tool_xml(spec.tool))}
  </worldbody>
  <contact><exclude body1="hand" body2="finger_l"/><exclude body1="hand" body2="finger_r"/></contact>
  <equality>{welds}</equality>
  <actuator>{actuators}</actuator>
</mujoco>"""


def arm_mjcf(tool: str | None = None) -> str:
    """MJCF text of the ADL arm alone (with a held tool): the robot model the offline assessment replays predicted
    trajectories on when a lab names no model of its own (adlpipe.offline.robot). Its end effector is the `tcp`
    site, its base the world origin (base_link)."""
    return f"""<mujoco model="adl_arm">
  <compiler angle="radian"/>
  <worldbody>
    {_arm_xml(_tool_xml(tool))}
  </worldbody>
  <contact><exclude body1="hand" body2="finger_l"/><exclude body1="hand" body2="finger_r"/></contact>
</mujoco>"""
