"""Robots: the built-in UR5 and Panda, URDF/MJCF import, robot meshes, and batched taxel
kinematics (poses and Jacobians of every taxel at once). May import `skin`, mujoco, trimesh."""
