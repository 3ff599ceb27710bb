"""The solver's material: Table 1's Mohr-Coulomb constants, stiffness scaling, the
optional mu(I) friction, in the form the kernels take (DESIGN §4)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..scene import Scene, SceneError
from . import mohr_coulomb as mc


@dataclass(frozen=True)
class Material:
    """Material constants of the Mohr-Coulomb model (paper Table 1 by default).

    Parameters
    ----------
    density : float
        kg/m³.
    youngs_modulus : float
        Pa, before stiffness scaling.
    poisson_ratio : float
        Dimensionless, in [0, 0.5).
    friction_angle_deg, dilation_angle_deg : float
        Degrees.
    cohesion : float
        Pa.
    wall_friction : float
        Coulomb coefficient between material and walls.
    stiffness_scaling : float
        E is divided by this factor (>= 1) for a larger stable dt.
    tension_cutoff : bool
        Cap the largest principal stress at c cot(phi).
    lost_contact : bool
        Keep the volume gained at the apex or cap as a gap that compaction closes
        stress-free (``mohr_coulomb.close_gap``), bounded by what the material around
        the particle lacks of its seeded packing (``kernels._bounded_gap``); on by
        default.
    friction_angle_limit_deg : float, optional
        The μ(I) rheology's limit angle, atan(μ2) > φ (``mohr_coulomb.rate_friction``);
        None (default): rate-independent Mohr-Coulomb, the paper's model.
    inertial_number_i0 : float
        The μ(I) rheology's I0.
    particle_diameter : float
        Grain diameter d, m (the μ(I) rheology's length).
    packing_fraction : float
        Solid fraction: the grain density is density / packing_fraction.
    """

    # no defaults here: every value comes from the scene, whose schema holds them
    density: float
    youngs_modulus: float
    poisson_ratio: float
    friction_angle_deg: float
    cohesion: float
    dilation_angle_deg: float
    wall_friction: float
    stiffness_scaling: float
    tension_cutoff: bool
    lost_contact: bool
    friction_angle_limit_deg: float | None
    inertial_number_i0: float
    particle_diameter: float
    packing_fraction: float
    bulk_viscosity_linear: float
    bulk_viscosity_quadratic: float

    @classmethod
    def from_scene(cls, scene: Scene) -> Material:
        m, s = scene["material"], scene["solver"]
        limit = m.get("friction_angle_limit_deg")
        if limit is not None and not limit > m["friction_angle_deg"]:
            raise SceneError(
                [
                    f"material.friction_angle_limit_deg = {limit!r} is out of range; allowed: "
                    f"> material.friction_angle_deg ({m['friction_angle_deg']!r}) and < 90"
                ]
            )
        return cls(
            density=m["density"],
            youngs_modulus=m["youngs_modulus"],
            poisson_ratio=m["poisson_ratio"],
            friction_angle_deg=m["friction_angle_deg"],
            cohesion=m["cohesion"],
            dilation_angle_deg=m["dilation_angle_deg"],
            wall_friction=m["wall_friction"],
            stiffness_scaling=s["stiffness_scaling"],
            tension_cutoff=s["tension_cutoff"],
            lost_contact=s["lost_contact"],
            friction_angle_limit_deg=None if limit is None else float(limit),
            inertial_number_i0=m["inertial_number_i0"],
            particle_diameter=m["particle_diameter"],
            packing_fraction=m["packing_fraction"],
            bulk_viscosity_linear=s["bulk_viscosity_linear"],
            bulk_viscosity_quadratic=s["bulk_viscosity_quadratic"],
        )

    def bulk_viscosity(self, h: float) -> tuple[float, float]:
        """(rho h b1 c_p, rho (b2 h)**2) for a cell h."""
        rho = self.density
        return (
            float(rho * h * self.bulk_viscosity_linear * self.p_wave_speed),
            float(rho * (self.bulk_viscosity_quadratic * h) ** 2),
        )

    @property
    def effective_modulus(self) -> float:
        return self.youngs_modulus / self.stiffness_scaling

    @property
    def bulk_shear(self) -> tuple[float, float]:
        k, g, _ = mc.elastic_constants(self.effective_modulus, self.poisson_ratio)
        return float(k), float(g)

    @property
    def p_wave_speed(self) -> float:
        return float(mc.p_wave_speed(self.effective_modulus, self.poisson_ratio, self.density))

    def return_arguments(self) -> tuple:
        """(K, G, sin phi, cos phi, c, sin psi, tension cutoff) for the stress update."""
        k, g = self.bulk_shear
        phi = math.radians(self.friction_angle_deg)
        psi = math.radians(self.dilation_angle_deg)
        if self.tension_cutoff and phi > 0:
            cutoff = self.cohesion / math.tan(phi)
        else:
            cutoff = 0.0
        values = (k, g, math.sin(phi), math.cos(phi), self.cohesion, math.sin(psi), cutoff)
        return tuple(float(a) for a in values)  # one compiled signature: all float64

    def rate_arguments(self) -> tuple[float, float, float]:
        """(μ2 − μs, I0, d sqrt(ρs)) of the μ(I) friction; rise 0 when rate-independent."""
        if self.friction_angle_limit_deg is None:
            return 0.0, 1.0, 0.0
        rise = math.tan(math.radians(self.friction_angle_limit_deg)) - math.tan(
            math.radians(self.friction_angle_deg)
        )
        grain_density = self.density / self.packing_fraction
        scale = self.particle_diameter * math.sqrt(grain_density)
        return float(rise), float(self.inertial_number_i0), float(scale)
