"""Designed dimensions of the demo leg, and the anatomical profile curves built from them.

Frame (straight, right leg): millimetres; x anterior, y to the subject's left (medial for the right
leg), z superior; the origin is the knee joint centre, mid-way between the two posterior condyle
circle centres, which both lie on the y axis (so the y axis *is* the flexion-extension axis).

Every function here is vectorised: arrays of z (and y, x) in, arrays out. The values are designed,
not measured; tests measure the generated mesh against them.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import PchipInterpolator

from kneegui.resources import resource_path

SKIN_PROFILE_FILE = "demo_leg_skin_profile.csv"

FloatArray = NDArray[np.float64]


def smoothstep(t: ArrayLike) -> FloatArray:
    """C1 ramp: 0 for t <= 0, 1 for t >= 1, ``3t^2 - 2t^3`` between."""
    t = np.clip(np.asarray(t, dtype=np.float64), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


@dataclass(frozen=True)
class DemoDesign:
    """The designed anatomy of the demo leg (straight pose, right side, mm and degrees).

    Attributes
    ----------
    lateral_radius, medial_radius : float
        Radii of the posterior condyle arcs in the sagittal plane (Jani et al. 2012 measured
        20.52 and 23.31 mm on the GM/UVA model).
    posterior_arc_top_deg, posterior_arc_bottom_deg : float
        Extent of the circular arcs above and below the condyle centres (the arc is exact there).
    initial_flexion_deg : float
        Angle between the femoral and tibial anatomical axes in the sagittal plane.
    patellar_flexion_ratio : float
        Share of the knee flexion given to the patella in the harmonic field that bends the skin.
    """

    lateral_radius: float = 20.5
    medial_radius: float = 23.3
    posterior_arc_top_deg: float = 35.0
    posterior_arc_bottom_deg: float = 45.0
    initial_flexion_deg: float = 9.0
    patellar_flexion_ratio: float = 0.65
    # extent of the model along the limb (straight pose)
    thigh_top_z: float = 400.0
    calf_bottom_z: float = -400.0
    # femur
    femur_shaft_centre: tuple[float, float] = (5.0, 0.0)
    femur_shaft_radius: float = 13.5
    lateral_epicondyle_y: float = -48.0
    medial_epicondyle_y: float = 51.0
    epicondyle_z: float = 8.0
    lateral_condyle_y: float = -41.0
    medial_condyle_y: float = 44.0
    notch_half_width: float = 11.0
    notch_roof_z: float = 6.0
    trochlea_x: float = 34.0
    trochlear_groove_depth: float = 6.0
    distal_rise: float = (
        6.0  # how much the distal femur rises from its flat posterior part to the front
    )
    # tibia (tibia frame = straight pose before the flexion rotation)
    tibia_shaft_centre: tuple[float, float] = (5.0, 3.0)
    tibia_shaft_radius: float = 12.0
    tibia_distal_radius: float = 14.5
    plateau_posterior_x: float = -11.5
    plateau_anterior_x: float = 38.0
    plateau_lateral_y: float = -40.0
    plateau_medial_y: float = 43.0
    plateau_rim_drop: float = 3.0
    tibial_slope_deg: float = 9.0  # posterior slope of the plateau (cancels the initial flexion)
    # plateau to condyle circle at the compartment centres (both cartilages; not modelled):
    # the plateaus sit this far beyond the posterior condyle circles, so that flexing about the
    # GCA keeps the tibia clear of the femur
    cartilage_gap: float = 3.5
    meniscus_max_height: float = 7.0
    min_flesh_thickness: float = 15.0  # soft minimum bone-to-skin distance
    # levels (straight pose, nominal z at the skin)
    tuberosity_z: tuple[float, float] = (-55.0, -40.0)
    fibula_head_top_z: float = -40.0
    patella_z: tuple[float, float] = (2.0, 45.0)
    mcl_z: tuple[float, float] = (-75.0, 16.0)
    lcl_top_z: float = 16.0
    ankle_joint_drop: float = 15.0  # tibio-talar joint centre below the distal cut
    skin_profile: tuple[tuple[float, ...], ...] = field(default=(), repr=False)

    # ------------------------------------------------------------------ derived values
    @property
    def lateral_arc_bottom_z(self) -> float:
        """z of the lowest point of the lateral posterior arc (the femur's posterior corner)."""
        return -self.lateral_radius * np.sin(np.radians(self.posterior_arc_bottom_deg))

    @property
    def medial_arc_bottom_z(self) -> float:
        """z of the lowest point of the medial posterior arc."""
        return -self.medial_radius * np.sin(np.radians(self.posterior_arc_bottom_deg))

    @property
    def knee_width(self) -> float:
        """Femoral epicondylar width (mm)."""
        return self.medial_epicondyle_y - self.lateral_epicondyle_y

    @property
    def flexion_rad(self) -> float:
        return float(np.radians(self.initial_flexion_deg))

    @cached_property
    def _skin(self) -> tuple[PchipInterpolator, ...]:
        table = np.array(self.skin_profile or load_skin_profile(), dtype=np.float64)
        return tuple(PchipInterpolator(table[:, 0], table[:, c]) for c in range(1, 5))

    # ------------------------------------------------------------------ skin
    def skin_ellipse(self, z: ArrayLike) -> FloatArray:
        """Skin cross-section at nominal height ``z``: (..., 4) centre x, centre y, semi-axes."""
        z = np.clip(np.asarray(z, dtype=np.float64), self.calf_bottom_z, self.thigh_top_z)
        return np.stack([f(z) for f in self._skin], axis=-1)

    # ------------------------------------------------------------------ femur
    def distal_flat_z(self, medial_weight: ArrayLike) -> FloatArray:
        """z of the flat posterior part of the distal femur (= bottom of the posterior arc).

        ``medial_weight`` is 0 on the lateral condyle, 1 on the medial one and in between across
        the intercondylar notch.
        """
        w = np.asarray(medial_weight, dtype=np.float64)
        radius = (1 - w) * self.lateral_radius + w * self.medial_radius
        return -radius * np.sin(np.radians(self.posterior_arc_bottom_deg))

    def distal_femur_z(self, x: ArrayLike, medial_weight: ArrayLike) -> FloatArray:
        """The distal femoral surface: flat behind x = 0, rising quadratically to the front."""
        x = np.asarray(x, dtype=np.float64)
        c = self.distal_rise / self.trochlea_x**2
        return self.distal_flat_z(medial_weight) + c * np.maximum(x, 0.0) ** 2

    def posterior_femur_x(self, medial_weight: ArrayLike, z: ArrayLike) -> FloatArray:
        """x of the femur's posterior surface: the condyle circle, then a decay to the shaft.

        Exact circle ``x = -sqrt(R^2 - z^2)`` for ``z <= R sin(top)``; above, an exponential that
        leaves the circle tangentially (C1) and tends to the metaphysis line ``x = -6``.
        """
        w = np.asarray(medial_weight, dtype=np.float64)
        z = np.asarray(z, dtype=np.float64)
        lat = self._posterior_arc_x(self.lateral_radius, z)
        med = self._posterior_arc_x(self.medial_radius, z)
        return (1 - w) * lat + w * med

    def _posterior_arc_x(self, radius: float, z: FloatArray) -> FloatArray:
        top = np.radians(self.posterior_arc_top_deg)
        z_top = radius * np.sin(top)
        x_top = -radius * np.cos(top)
        x_far = -6.0
        lam = (x_far - x_top) / np.tan(top)
        zc = np.clip(z, -radius * np.sin(np.radians(self.posterior_arc_bottom_deg)), z_top)
        on_arc = -np.sqrt(radius**2 - zc**2)
        above = x_far + (x_top - x_far) * np.exp(-np.maximum(z - z_top, 0.0) / lam)
        return np.where(z <= z_top, on_arc, above)

    def anterior_femur_x(self, y: ArrayLike) -> FloatArray:
        """x of the trochlea: lateral facet a little higher, groove in the middle."""
        y = np.asarray(y, dtype=np.float64)
        lateral_facet = 2.0 / (1.0 + np.exp(y / 8.0))
        groove = self.trochlear_groove_depth * np.exp(-((y / 14.0) ** 2))
        return self.trochlea_x + lateral_facet - groove

    def femur_side_y(self, z: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Lateral and medial extent of the distal femur (epicondyles peak at ``epicondyle_z``)."""
        z = np.asarray(z, dtype=np.float64)
        bump = np.exp(-(((z - self.epicondyle_z) / 14.0) ** 2))
        lat = self.lateral_condyle_y + (self.lateral_epicondyle_y - self.lateral_condyle_y) * bump
        med = self.medial_condyle_y + (self.medial_epicondyle_y - self.medial_condyle_y) * bump
        return lat, med

    def femur_knee_weight(self, z: ArrayLike) -> FloatArray:
        """1 where the femur has its distal (condylar) shape, 0 on the shaft."""
        return 1.0 - smoothstep((np.asarray(z, dtype=np.float64) - 25.0) / 70.0)

    def meniscus_height_limit(self, x: ArrayLike) -> FloatArray:
        """Largest meniscus height over the plateau at ``x`` (mm).

        ``meniscus_max_height`` behind x = 0, where the condyles sweep over the menisci as the
        knee flexes; in front it grows as the distal femur rises towards the trochlea, so the
        joint space above the anterior horns stays as thin as behind (a thicker one gives the
        flesh cells around it aspect ratios above 10 on fine meshes).
        """
        x = np.asarray(x, dtype=np.float64)
        rise = self.distal_rise / self.trochlea_x**2 * np.maximum(x, 0.0) ** 2
        return self.meniscus_max_height + rise

    # ------------------------------------------------------------------ tibia (tibia frame)
    def tibia_knee_weight(self, z: ArrayLike) -> FloatArray:
        """1 where the tibia has its plateau shape, 0 on the shaft."""
        return smoothstep((np.asarray(z, dtype=np.float64) + 140.0) / 102.0)

    def tibia_shaft_radius_at(self, z: ArrayLike) -> FloatArray:
        """Shaft radius, widening towards the distal tibia."""
        z = np.asarray(z, dtype=np.float64)
        t = smoothstep((-250.0 - z) / (-250.0 - self.calf_bottom_z))
        return self.tibia_shaft_radius + (self.tibia_distal_radius - self.tibia_shaft_radius) * t

    def plateau_centre_z(self, medial_weight: ArrayLike) -> FloatArray:
        """Plateau height at x = 0 in the tibia frame: ``cartilage_gap`` beyond the condyle
        circle, whose centre is the F-E axis.

        Flexion turns the tibia about that axis, so the plateau keeps its distance from it and
        the circular posterior condyle never reaches it at any flexion (seated under the flat
        distal femur instead, 0.7 R below the axis, the plateau lay 3.3 mm inside the medial
        condyle's circle and the tibia went that deep into the femur from 60 deg on).
        """
        w = np.asarray(medial_weight, dtype=np.float64)
        radius = (1 - w) * self.lateral_radius + w * self.medial_radius
        return -(radius + self.cartilage_gap) / np.cos(self.flexion_rad)

    def plateau_z(self, x: ArrayLike, y: ArrayLike, medial_weight: ArrayLike) -> FloatArray:
        """Tibial plateau surface (tibia frame): posterior slope, rim dropping at the periphery."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        slope = np.tan(np.radians(self.tibial_slope_deg)) * x
        rho = np.minimum(
            np.hypot((x - 13.0) / 26.0, (y + 22.0) / 16.0),
            np.hypot((x - 13.0) / 26.0, (y - 24.0) / 17.0),
        )
        rim = self.plateau_rim_drop * smoothstep((rho - 0.5) / 0.7)
        return self.plateau_centre_z(medial_weight) + slope - rim


def load_skin_profile() -> tuple[tuple[float, ...], ...]:
    """The skin cross-section table (z, centre x, centre y, semi-axis x, semi-axis y), in mm."""
    rows = []
    with open(resource_path(SKIN_PROFILE_FILE), newline="") as f:
        for row in csv.DictReader(f):
            rows.append(
                tuple(
                    float(row[k])
                    for k in (
                        "z_mm",
                        "centre_x_mm",
                        "centre_y_mm",
                        "semi_axis_x_mm",
                        "semi_axis_y_mm",
                    )
                )
            )
    return tuple(sorted(rows))
