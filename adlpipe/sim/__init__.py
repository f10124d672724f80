"""The MuJoCo ADL world: a table, a seated manikin, task objects, a 7-DoF arm with a gripper and an RGB-D camera.

World frame == the robot's base_link frame (origin on the table top at the robot's base, +y towards the manikin,
+z up), so trajectories recorded in base_link can be replayed without a further transform.
"""

import os

# Headless rendering: EGL works on machines without a display. Respect a user's own choice.
os.environ.setdefault("MUJOCO_GL", "egl")
