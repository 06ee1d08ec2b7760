"""The three-jaw laparoscopic grasper (Mirbagheri & Farahmand 2013), as rigid planar jaws.

Three jaws 120 deg apart around the grasper axis. A parallelogram mechanism keeps each jaw's planar inner
face parallel to the axis; the faces are tangent to a "hollow cylinder" of radius R(t) about the axis
(the paper's Fig. 2), so closing the jaws = shrinking R. Geometry in the grasper frame:

* axis ``a`` (unit) points from the handle toward the jaw tips; the *tip point* ``c`` lies on the axis at
  the jaw tips; the jaws span the axial coordinate s = (x - c).a in [-jaw_length, 0];
* jaw k's face has outward direction u_k = cos(2 pi k/3) e1 + sin(2 pi k/3) e2 (e1 normal to the axis,
  e2 = a x e1); its plane is (x - c).u_k = R, its width runs along a x u_k, |lateral| <= width/2;
* the grasper moves as a whole with the pull velocity; the faces move by dR/dt along u_k when closing.

Adjacent faces meet at the corners of an equilateral triangle of inradius R, a lateral distance
sqrt(3) R from each face centre; faces wider than 2 sqrt(3) R_min would overlap when closed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .config import ConfigError, NonNegative, Positive, config_dataclass


@config_dataclass
class GrasperParams:
    """Jaw geometry, limits and tool-tissue friction (SI units)."""

    jaw_length_m: Positive = 0.030
    jaw_width_m: Positive = 0.010
    #: how far behind its face plane a node is still caught by a jaw (its thickness), m
    jaw_depth_m: Positive = 0.004
    #: radius of the fully open jaws, m
    open_radius_m: Positive = 0.035
    #: radius of the fully closed jaws, m
    min_radius_m: Positive = 0.004
    #: static friction coefficient jaw/tissue
    mu: NonNegative = 0.6
    #: kinetic friction coefficient (None: equal to ``mu``); must not exceed ``mu``
    mu_kinetic: NonNegative | None = None
    #: largest closing speed the actuator can command, m/s (radius rate)
    max_closing_speed_m_s: Positive = 0.004
    #: largest pull speed of the whole grasper, m/s
    max_pull_speed_m_s: Positive = 0.02

    def __post_init__(self) -> None:
        if self.mu_kinetic is not None and self.mu_kinetic > self.mu:
            raise ConfigError(f"mu_kinetic = {self.mu_kinetic} is out of range; allowed [0, mu = {self.mu}]")
        if self.min_radius_m >= self.open_radius_m:
            raise ConfigError(
                f"min_radius_m = {self.min_radius_m} must be smaller than open_radius_m = {self.open_radius_m}"
            )
        overlap_radius = self.jaw_width_m / (2.0 * math.sqrt(3.0))
        if self.min_radius_m < overlap_radius:
            raise ConfigError(
                f"jaws overlap at the minimum radius: min_radius_m = {self.min_radius_m} m must be >= "
                f"jaw_width_m / (2 sqrt 3) = {overlap_radius:.5f} m for jaw_width_m = {self.jaw_width_m} m"
            )

    @property
    def mu_k(self) -> float:
        return self.mu if self.mu_kinetic is None else self.mu_kinetic


@dataclass(frozen=True)
class GrasperPose:
    """Where the grasper is: tip point (m), axis (unit, handle -> tip) and the azimuth-0 direction."""

    tip: np.ndarray
    axis: np.ndarray
    e1: np.ndarray

    @classmethod
    def from_axis(cls, tip, axis, up_hint=(0.0, 0.0, 1.0)) -> "GrasperPose":
        """Pose with jaw 0 facing the component of ``up_hint`` normal to the axis."""
        tip = np.asarray(tip, dtype=np.float64)
        a = np.asarray(axis, dtype=np.float64)
        if tip.shape != (3,) or a.shape != (3,) or not (np.all(np.isfinite(tip)) and np.all(np.isfinite(a))):
            raise ConfigError("grasper pose: tip and axis must be 3 finite numbers each")
        na = np.linalg.norm(a)
        if na == 0:
            raise ConfigError("grasper pose: axis must be a non-zero vector")
        a = a / na
        h = np.asarray(up_hint, dtype=np.float64)
        e1 = h - a * (h @ a)
        if np.linalg.norm(e1) < 1e-6:  # hint parallel to the axis: pick any normal
            e1 = np.cross(a, [1.0, 0.0, 0.0])
            if np.linalg.norm(e1) < 1e-6:
                e1 = np.cross(a, [0.0, 1.0, 0.0])
        e1 = e1 / np.linalg.norm(e1)
        return cls(tip=tip, axis=a, e1=e1)

    def rotated(self, azimuth_rad: float) -> "GrasperPose":
        """The same pose with the jaws rotated about the axis by ``azimuth_rad``."""
        e2 = np.cross(self.axis, self.e1)
        e1 = math.cos(azimuth_rad) * self.e1 + math.sin(azimuth_rad) * e2
        return GrasperPose(self.tip.copy(), self.axis.copy(), e1)

    def jaw_directions(self) -> np.ndarray:
        """(3,3) outward unit direction u_k of each jaw face."""
        e2 = np.cross(self.axis, self.e1)
        ang = 2.0 * np.pi * np.arange(3) / 3.0
        return np.cos(ang)[:, None] * self.e1 + np.sin(ang)[:, None] * e2


def jaw_face_corners(pose: GrasperPose, radius: float, params: GrasperParams) -> np.ndarray:
    """(3,4,3) corners of each jaw face (for drawing): [tip-left, tip-right, back-right, back-left]."""
    u = pose.jaw_directions()
    out = np.empty((3, 4, 3))
    hw = 0.5 * params.jaw_width_m
    for k in range(3):
        lat = np.cross(pose.axis, u[k])
        centre_tip = pose.tip + radius * u[k]
        back = -params.jaw_length_m * pose.axis
        out[k] = [centre_tip - hw * lat, centre_tip + hw * lat,
                  centre_tip + back + hw * lat, centre_tip + back - hw * lat]
    return out


def cylindrical_coordinates(points: np.ndarray, pose: GrasperPose) -> np.ndarray:
    """(n,3) [rho, phi, s] of points about the grasper axis (phi from e1, s along the axis from the tip)."""
    r = np.asarray(points) - pose.tip
    e2 = np.cross(pose.axis, pose.e1)
    s = r @ pose.axis
    p1 = r @ pose.e1
    p2 = r @ e2
    return np.stack([np.hypot(p1, p2), np.arctan2(p2, p1), s], axis=-1)


def reachable_radius(points: np.ndarray, pose: GrasperPose, params: GrasperParams) -> np.ndarray:
    """(3,) for each jaw, the largest face radius at which a node lies on that face's footprint (0: none).

    A jaw can touch the tissue only while its radius is below this value: a jaw whose value is below
    ``min_radius_m`` never makes contact (e.g. a grasper axis that misses the tissue). A node counts if its
    axial coordinate is on the jaws and its lateral offset from the face's centre line is within half the
    jaw width (:func:`.contact.jaw_reach`, which each episode's start radius uses too).
    """
    from .contact import jaw_reach

    points = np.ascontiguousarray(points, dtype=np.float64)
    return np.array(jaw_reach(points, np.arange(len(points)), tuple(pose.tip), tuple(pose.axis), tuple(pose.e1),
                              float(params.jaw_length_m), 0.5 * float(params.jaw_width_m)))


def start_radius(reach, params: GrasperParams) -> float:
    """The radius the jaws open to at a start, clear of ``reach`` (:func:`.contact.jaw_start_radius`)."""
    from .contact import jaw_start_radius

    return float(jaw_start_radius(tuple(float(r) for r in reach), float(params.open_radius_m)))
