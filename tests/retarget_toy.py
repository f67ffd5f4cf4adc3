"""A small OP3-like test humanoid (MJCF text) for the retarget tests.

Written here so the retarget tests do not depend on the bundled robot's file:
free root, 2×6-DOF legs, 2×3-DOF arms, a 2-DOF head, keypoint sites, capsules,
a "stand" keyframe, and some joints with non-zero reference angles and tilted axes
so that the kinematics are exercised beyond the trivial case.
"""

TOY_XML = """
<mujoco model="toy">
  <compiler angle="radian" boundmass="0.01" boundinertia="1e-5"/>
  <default><geom contype="0" conaffinity="0"/></default>
  <worldbody>
    <geom name="floor" type="plane" size="2 2 0.1"/>
    <body name="torso" pos="0 0 0.29">
      <freejoint name="root"/>
      <geom name="torso_g" type="box" size="0.04 0.06 0.07" pos="0 0 0.07" mass="1.5"/>
      <site name="pelvis" pos="0 0 0"/>
      <body name="head" pos="0 0 0.16">
        <joint name="head_pan" axis="0 0 1" range="-1.5 1.5"/>
        <body name="head_tilt_link" pos="0 0 0.01">
          <joint name="head_tilt" axis="0 1 0" range="-0.8 0.8"/>
          <geom type="sphere" size="0.04" pos="0 0 0.04" mass="0.3"/>
          <site name="head" pos="0.01 0 0.05"/>
        </body>
      </body>
      <body name="r_sho" pos="0 -0.08 0.13">
        <joint name="r_sho_pitch" axis="0 1 0" range="-3.0 3.0"/>
        <site name="r_shoulder" pos="0 0 0"/>
        <body name="r_upper_arm" pos="0 -0.02 0" quat="0.9998 0.02 0 0">
          <joint name="r_sho_roll" axis="1 0 0" range="-1.6 0.3"/>
          <geom name="r_upper_arm_g" type="capsule" fromto="0 0 0 0 0 -0.09" size="0.015" mass="0.2"/>
          <body name="r_forearm" pos="0 0 -0.09">
            <joint name="r_el" axis="0 1 0" range="-2.5 0.1" ref="0.05"/>
            <site name="r_elbow" pos="0 0 0"/>
            <geom name="r_forearm_g" type="capsule" fromto="0 0 0 0 0 -0.1" size="0.015" mass="0.15"/>
            <site name="r_hand" pos="0 0 -0.1"/>
          </body>
        </body>
      </body>
      <body name="l_sho" pos="0 0.08 0.13">
        <joint name="l_sho_pitch" axis="0 1 0" range="-3.0 3.0"/>
        <site name="l_shoulder" pos="0 0 0"/>
        <body name="l_upper_arm" pos="0 0.02 0">
          <joint name="l_sho_roll" axis="1 0 0" range="-0.3 1.6"/>
          <geom name="l_upper_arm_g" type="capsule" fromto="0 0 0 0 0 -0.09" size="0.015" mass="0.2"/>
          <body name="l_forearm" pos="0 0 -0.09">
            <joint name="l_el" axis="0 1 0" range="-2.5 0.1"/>
            <site name="l_elbow" pos="0 0 0"/>
            <geom name="l_forearm_g" type="capsule" fromto="0 0 0 0 0 -0.1" size="0.015" mass="0.15"/>
            <site name="l_hand" pos="0 0 -0.1"/>
          </body>
        </body>
      </body>
      <body name="r_hip_yaw_link" pos="0 -0.035 -0.01">
        <joint name="r_hip_yaw" axis="0 0 1" range="-1.0 1.0"/>
        <site name="r_hip" pos="0 0 -0.02"/>
        <body name="r_hip_roll_link" pos="0 0 -0.02">
          <joint name="r_hip_roll" axis="1 0 0" range="-0.7 0.5"/>
          <body name="r_thigh" pos="0 0 0">
            <joint name="r_hip_pitch" axis="0 1 0" range="-1.8 0.6" pos="0 0 0.001"/>
            <geom name="r_thigh_g" type="capsule" fromto="0 0 0 0 0 -0.11" size="0.02" mass="0.4"/>
            <body name="r_shin" pos="0 0 -0.11">
              <joint name="r_knee" axis="0 1 0" range="0 2.4"/>
              <site name="r_knee" pos="0 0 0"/>
              <geom name="r_shin_g" type="capsule" fromto="0 0 0 0 0 -0.11" size="0.02" mass="0.3"/>
              <body name="r_ank" pos="0 0 -0.11">
                <joint name="r_ank_pitch" axis="0 1 0" range="-1.2 1.2"/>
                <body name="r_foot" pos="0 0 0">
                  <joint name="r_ank_roll" axis="1 0 0.02" range="-0.6 0.6"/>
                  <site name="r_ankle" pos="0 0 0"/>
                  <geom name="r_foot_g" type="box" size="0.05 0.025 0.005" pos="0.01 0 -0.025" mass="0.1"/>
                  <site name="r_toe" pos="0.06 0 -0.03"/>
                  <site name="r_sole" pos="0.01 0 -0.03"/>
                </body>
              </body>
            </body>
          </body>
        </body>
      </body>
      <body name="l_hip_yaw_link" pos="0 0.035 -0.01">
        <joint name="l_hip_yaw" axis="0 0 1" range="-1.0 1.0"/>
        <site name="l_hip" pos="0 0 -0.02"/>
        <body name="l_hip_roll_link" pos="0 0 -0.02">
          <joint name="l_hip_roll" axis="1 0 0" range="-0.5 0.7"/>
          <body name="l_thigh" pos="0 0 0">
            <joint name="l_hip_pitch" axis="0 1 0" range="-1.8 0.6"/>
            <geom name="l_thigh_g" type="capsule" fromto="0 0 0 0 0 -0.11" size="0.02" mass="0.4"/>
            <body name="l_shin" pos="0 0 -0.11">
              <joint name="l_knee" axis="0 1 0" range="0 2.4"/>
              <site name="l_knee" pos="0 0 0"/>
              <geom name="l_shin_g" type="capsule" fromto="0 0 0 0 0 -0.11" size="0.02" mass="0.3"/>
              <body name="l_ank" pos="0 0 -0.11">
                <joint name="l_ank_pitch" axis="0 1 0" range="-1.2 1.2"/>
                <body name="l_foot" pos="0 0 0">
                  <joint name="l_ank_roll" axis="1 0 0" range="-0.6 0.6"/>
                  <site name="l_ankle" pos="0 0 0"/>
                  <geom name="l_foot_g" type="box" size="0.05 0.025 0.005" pos="0.01 0 -0.025" mass="0.1"/>
                  <site name="l_toe" pos="0.06 0 -0.03"/>
                  <site name="l_sole" pos="0.01 0 -0.03"/>
                </body>
              </body>
            </body>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <keyframe>
    <key name="stand" qpos="0 0 0.28 1 0 0 0  0 0  0 -1.2 -0.3  0 1.2 -0.3  0 0 -0.2 0.4 -0.2 0  0 0 -0.2 0.4 -0.2 0"/>
  </keyframe>
</mujoco>
"""

#: A retarget profile for the toy humanoid (the YAML mapping, as a dict).
TOY_PROFILE = {
    "robot": "toy",
    "root": "pelvis",
    "keypoints": {
        "pelvis": {"site": "pelvis", "weight": 2.0},
        "head": {"site": "head", "weight": 0.5},
        "left_hip": {"site": "l_hip"},
        "right_hip": {"site": "r_hip"},
        "left_knee": {"site": "l_knee"},
        "right_knee": {"site": "r_knee"},
        "left_ankle": {"site": "l_ankle", "weight": 2.0},
        "right_ankle": {"site": "r_ankle", "weight": 2.0},
        "left_foot": {"site": "l_toe"},
        "right_foot": {"site": "r_toe"},
        "left_shoulder": {"site": "l_shoulder"},
        "right_shoulder": {"site": "r_shoulder"},
        "left_elbow": {"site": "l_elbow"},
        "right_elbow": {"site": "r_elbow"},
        "left_wrist": {"site": "l_hand", "weight": 1.5},
        "right_wrist": {"site": "r_hand", "weight": 1.5},
    },
    "velocity_limits": {"default": 6.0},
    "capsules": {
        "torso": {"body": "torso", "from": [0, 0, 0.03], "to": [0, 0, 0.11], "radius": 0.05},
        "l_forearm": {"geom": "l_forearm_g"},
        "r_forearm": {"geom": "r_forearm_g"},
        "l_shin": {"geom": "l_shin_g"},
        "r_shin": {"geom": "r_shin_g"},
    },
    "collision_pairs": [["l_forearm", "torso"], ["r_forearm", "torso"], ["l_shin", "r_shin"]],
    "feet": {"left": {"body": "l_foot", "geom": "l_foot_g"}, "right": {"body": "r_foot", "geom": "r_foot_g"}},
    "posture_weight": 0.02,
}


def toy_robot(fixed_base: bool = False, **changes):
    """The toy humanoid bound to TOY_PROFILE (with top-level ``changes``)."""
    from retarget.profile import RetargetProfile
    from retarget.robot import robot_from_xml_string

    data = dict(TOY_PROFILE, **changes)
    return robot_from_xml_string(TOY_XML, RetargetProfile.from_dict(data, source="toy.yaml"), fixed_base=fixed_base)
