"""SE(2) math over batches: poses are ``(..., 3)`` arrays ``(x, y, yaw)``.

Convention (see ``csr_core.types``): ``a_T_c = compose(a_T_b, b_T_c)``;
``transform_points(a_T_b, points_xy_b) -> points_xy_a``.
"""

from __future__ import annotations

import numpy as np


def wrap_angle(angle_rad: np.ndarray | float) -> np.ndarray | float:
    """Wrap to [-pi, pi)."""
    return (np.asarray(angle_rad) + np.pi) % (2 * np.pi) - np.pi


def compose(a_T_b: np.ndarray, b_T_c: np.ndarray) -> np.ndarray:
    a_T_b = np.asarray(a_T_b, float)
    b_T_c = np.asarray(b_T_c, float)
    c, s = np.cos(a_T_b[..., 2]), np.sin(a_T_b[..., 2])
    x = a_T_b[..., 0] + c * b_T_c[..., 0] - s * b_T_c[..., 1]
    y = a_T_b[..., 1] + s * b_T_c[..., 0] + c * b_T_c[..., 1]
    return np.stack([x, y, wrap_angle(a_T_b[..., 2] + b_T_c[..., 2])], axis=-1)


def inverse(a_T_b: np.ndarray) -> np.ndarray:
    a_T_b = np.asarray(a_T_b, float)
    c, s = np.cos(a_T_b[..., 2]), np.sin(a_T_b[..., 2])
    x = -(c * a_T_b[..., 0] + s * a_T_b[..., 1])
    y = -(-s * a_T_b[..., 0] + c * a_T_b[..., 1])
    return np.stack([x, y, wrap_angle(-a_T_b[..., 2])], axis=-1)


def between(a_T_b: np.ndarray, a_T_c: np.ndarray) -> np.ndarray:
    """``b_T_c = inverse(a_T_b) @ a_T_c`` (relative pose, e.g. odometry increments)."""
    return compose(inverse(a_T_b), a_T_c)


def transform_points(a_T_b: np.ndarray, points_xy_b: np.ndarray) -> np.ndarray:
    """Apply one pose ``(3,)`` to points ``(M, 2)``."""
    a_T_b = np.asarray(a_T_b, float)
    c, s = np.cos(a_T_b[2]), np.sin(a_T_b[2])
    rot = np.array([[c, -s], [s, c]])
    return np.asarray(points_xy_b, float) @ rot.T + a_T_b[:2]


def heading_deg_to_yaw_rad(heading_deg: np.ndarray | float) -> np.ndarray | float:
    """Course clockwise from north (degrees) -> yaw counter-clockwise from east (radians)."""
    return wrap_angle(np.pi / 2 - np.radians(heading_deg))


def yaw_rad_to_heading_deg(yaw_rad: np.ndarray | float) -> np.ndarray | float:
    """Inverse of :func:`heading_deg_to_yaw_rad`, in [0, 360)."""
    return np.mod(90.0 - np.degrees(yaw_rad), 360.0)
