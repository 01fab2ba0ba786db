"""Attitude: rotations between the ICRS and the camera frame, Wahba's problem
with its covariance, and the attitude of a whole sequence (constant body rate).

``rotation_matrix`` everywhere maps ICRS unit vectors to camera-frame unit
vectors; see :mod:`app.attitude.rotations` for RA/Dec/roll and quaternions.
"""

from app.attitude.rotations import (angle_between, boresight_and_roll_error, propagate, quaternion_from_rotation,
                                    radec_roll_from_rotation, rotation_angle_between,
                                    rotation_angles_between, rotation_from_pair,
                                    rotation_from_quaternion, rotation_from_radec_roll, solve_wahba)
from app.attitude.wahba import wahba_covariance

__all__ = ["angle_between", "boresight_and_roll_error", "propagate", "quaternion_from_rotation", "radec_roll_from_rotation",
           "rotation_angle_between", "rotation_angles_between", "rotation_from_pair", "rotation_from_quaternion",
           "rotation_from_radec_roll", "solve_wahba", "wahba_covariance"]
