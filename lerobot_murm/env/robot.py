"""The Franka Panda: loading, 4-DoF end-effector control and instant placement by IK.

The stock `franka_panda/panda.urdf` of pybullet_data has visual meshes of 7k-22k faces
per link, which makes CPU rendering ~15x slower than the scene needs at 48x48 pixels.
`lowpoly_panda_urdf()` writes a copy whose visuals are the collision meshes
(200-1300 faces) and the robot is then coloured per link.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pybullet
import pybullet_data

ARM_JOINTS = tuple(range(7))
FINGER_JOINTS = (9, 10)
EE_LINK = 11  # panda_grasptarget: between the fingertips
ARM_FORCES = (87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0)
FINGER_FORCE = 40.0
MAX_FINGER_WIDTH = 0.08
# A comfortable elbow-up posture; IK null space pulls towards it so the arm never folds oddly.
REST_POSE = (0.0, 0.2, 0.0, -2.0, 0.0, 2.2, np.pi / 4)
GRIPPER_DOWN = pybullet.getQuaternionFromEuler([np.pi, 0.0, 0.0])

STOCK_URDF = Path(pybullet_data.getDataPath()) / "franka_panda" / "panda.urdf"

LINK_COLOURS = {
    **dict.fromkeys(range(-1, 7), (0.92, 0.92, 0.92, 1.0)),
    7: (0.25, 0.25, 0.25, 1.0),
    8: (0.92, 0.92, 0.92, 1.0),
    9: (0.25, 0.25, 0.25, 1.0),
    10: (0.25, 0.25, 0.25, 1.0),
}


def lowpoly_panda_urdf() -> Path:
    """Path of the stock Panda URDF rewritten to render its collision meshes."""
    mesh_dir = STOCK_URDF.parent / "meshes"
    text = STOCK_URDF.read_text()
    text = text.replace("package://meshes/visual/", f"{mesh_dir}/collision/")
    text = text.replace("package://meshes/collision/", f"{mesh_dir}/collision/")
    out_dir = Path(tempfile.gettempdir()) / "lerobot-murm-assets"  # not an importable name
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "panda_lowpoly.urdf"
    if not path.exists() or path.read_text() != text:
        tmp = path.with_suffix(f".{np.random.default_rng().integers(1 << 30)}.tmp")
        tmp.write_text(text)
        tmp.replace(path)  # atomic: parallel workers never read half a file
    return path


class Panda:
    """A Panda with its base at the world origin, gripper pointing down, fixed yaw."""

    def __init__(self, client, lowpoly: bool = True):
        self._client = client
        urdf = lowpoly_panda_urdf() if lowpoly else STOCK_URDF
        self.body = client.loadURDF(
            str(urdf),
            basePosition=[0, 0, 0],
            useFixedBase=True,
            flags=pybullet.URDF_ENABLE_CACHED_GRAPHICS_SHAPES,
        )
        if lowpoly:
            for link, rgba in LINK_COLOURS.items():
                client.changeVisualShape(self.body, link, rgbaColor=rgba)
        for finger in FINGER_JOINTS:
            client.changeDynamics(self.body, finger, lateralFriction=1.5, spinningFriction=0.002)
        self._lower = [client.getJointInfo(self.body, j)[8] for j in ARM_JOINTS]
        self._upper = [client.getJointInfo(self.body, j)[9] for j in ARM_JOINTS]

    # --- state -----------------------------------------------------------------------
    def ee_position(self) -> np.ndarray:
        state = self._client.getLinkState(self.body, EE_LINK, computeForwardKinematics=True)
        return np.asarray(state[4], dtype=np.float64)

    def finger_width(self) -> float:
        return float(sum(self._client.getJointState(self.body, j)[0] for j in FINGER_JOINTS))

    # --- control ---------------------------------------------------------------------
    def inverse_kinematics(self, position: np.ndarray) -> list[float]:
        solution = self._client.calculateInverseKinematics(
            self.body,
            EE_LINK,
            targetPosition=list(position),
            targetOrientation=GRIPPER_DOWN,
            lowerLimits=self._lower,
            upperLimits=self._upper,
            jointRanges=[u - lo for lo, u in zip(self._lower, self._upper, strict=True)],
            restPoses=list(REST_POSE),
            maxNumIterations=50,
            residualThreshold=1e-4,
        )
        return list(solution[: len(ARM_JOINTS)])

    def command(self, ee_target: np.ndarray, close_gripper: bool) -> None:
        """Set motor targets: the arm towards `ee_target`, the fingers closed or open."""
        self._client.setJointMotorControlArray(
            self.body,
            ARM_JOINTS,
            pybullet.POSITION_CONTROL,
            targetPositions=self.inverse_kinematics(ee_target),
            forces=ARM_FORCES,
        )
        finger_target = 0.0 if close_gripper else MAX_FINGER_WIDTH / 2
        self._client.setJointMotorControlArray(
            self.body,
            FINGER_JOINTS,
            pybullet.POSITION_CONTROL,
            targetPositions=[finger_target, finger_target],
            forces=[FINGER_FORCE, FINGER_FORCE],
        )

    def teleport(self, ee_position: np.ndarray, finger_width: float) -> None:
        """Put the end-effector at `ee_position` at once (no physics), by repeated IK."""
        for _ in range(4):  # IK from a far posture converges in a few rounds
            for joint, angle in zip(ARM_JOINTS, self.inverse_kinematics(ee_position), strict=True):
                self._client.resetJointState(self.body, joint, angle)
        for joint in FINGER_JOINTS:
            self._client.resetJointState(self.body, joint, finger_width / 2)

    def hold(self, close_gripper: bool) -> None:
        """Motor targets equal to the present posture (after a teleport)."""
        self.command(self.ee_position(), close_gripper)

    def reset_to_rest(self) -> None:
        for joint, angle in zip(ARM_JOINTS, REST_POSE, strict=True):
            self._client.resetJointState(self.body, joint, angle)
