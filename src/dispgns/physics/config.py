"""Parameters of the ground-truth suspension model (SI units throughout)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from dispgns._config import check_fields, config_from_mapping

__all__ = ["PhysicsConfig"]


@dataclasses.dataclass(frozen=True)
class PhysicsConfig:
    """The sedimenting-disk model of Hashemi & Izadkhah (2025), in SI units.

    Disks of radius ``a_i`` and thickness ``thickness`` (D = 2) or spheres
    (D = 3) move in the box ``[-h_0, h_0] x ... x [-h_{D-1}, h_{D-1}]`` (the
    half-sizes ``h_d`` from ``box_half_size``) under buoyant weight (along the
    last axis), linear drag ``-drag * a_i * v_i`` and the truncated
    Lennard-Jones pair force, integrated with explicit Euler.

    Attributes:
      thickness: disk thickness ``s`` in m (only used for D = 2 volumes).
      density: particle density ``rho`` in kg/m^3.
      fluid_density: liquid density ``rho_f`` in kg/m^3.
      gravity: ``g`` in m/s^2. The authors' generator uses 9.8066 (the paper
        prints 9.81).
      box_half_size: half-size of the box in m: one float ``L`` for the square
        (cubic) box ``[-L, L]^D`` of the paper, or one half-size per axis,
        e.g. ``(0.4, 0.1)`` for a 2-D container four times wider than tall
        (the last axis is vertical). Walls on every face. A tuple of equal
        half-sizes gives bit-identical results to the float.
      drag: ``k`` in kg/(m s); drag force ``-k a_i v_i``.
      lj_exponent: ``p``; ``U(r) = 4 U0 [(sigma/r)^(2p) - (sigma/r)^p]``.
      well_depth_coeff: ``U0 = well_depth_coeff * sigma^2`` (J, with sigma in m).
      min_distance_coeff: ``r_m = min_distance_coeff * min(a_i, a_j)``; below
        ``r_m`` the pair force keeps its magnitude at ``r_m``.
      restitution: ``gamma``; a wall collision scales the whole velocity by
        ``sqrt(gamma)``.
      dt: Euler step in s.
      cutoff: ``None`` for the exact model (every pair interacts, as the
        authors do), or an interaction cut-off distance in m. With a finite
        cut-off, pairs are found with a jax-md cell list and the cost grows
        linearly with the number of particles.
      neighbor_skin: extra distance in m added to ``cutoff`` when building
        neighbour lists, so that lists are rebuilt only after some particle
        moved by more than half of it. Unused when ``cutoff`` is ``None``.
    """

    thickness: float = 2e-3
    density: float = 2300.0
    fluid_density: float = 1000.0
    gravity: float = 9.8066
    box_half_size: float | tuple[float, ...] = 0.1
    drag: float = 1.25
    lj_exponent: int = 6
    well_depth_coeff: float = 0.025
    min_distance_coeff: float = 1.75
    restitution: float = 0.8
    dt: float = 1e-4
    cutoff: float | None = None
    neighbor_skin: float = 2e-3

    def __post_init__(self):
        for field in dataclasses.fields(self):
            # numpy scalars become Python floats: the config stays hashable and JSON-serialisable.
            value = getattr(self, field.name)
            if isinstance(value, np.floating) or (isinstance(value, np.integer) and field.name != "lj_exponent"):
                object.__setattr__(self, field.name, float(value))
        self._check_box()
        check_fields(
            self,
            integers={"lj_exponent": 1},
            positive=("thickness", "density", "dt"),
            nonnegative=("fluid_density", "gravity", "drag", "well_depth_coeff", "min_distance_coeff", "neighbor_skin"),
        )
        if not (0.0 < self.restitution <= 1.0):
            raise ValueError(f"PhysicsConfig.restitution must lie in (0, 1], got {self.restitution!r}")
        cutoff = self.cutoff
        if cutoff is not None and not (isinstance(cutoff, int | float) and math.isfinite(cutoff) and cutoff > 0):
            raise ValueError(f"PhysicsConfig.cutoff must be None or a distance > 0 in m, got {self.cutoff!r}")

    def _check_box(self):
        value = self.box_half_size
        if isinstance(value, str):
            # Command-line and YAML text: "0.4,0.1" or "0.1".
            try:
                parts = [float(part) for part in value.replace("(", "").replace(")", "").split(",") if part.strip()]
            except ValueError:
                parts = []
            value = parts[0] if len(parts) == 1 else tuple(parts) if parts else value
        elif isinstance(value, list | tuple | np.ndarray):
            value = tuple(
                float(v) if isinstance(v, int | float | np.number) and not isinstance(v, bool) else v
                for v in np.asarray(value, dtype=object).ravel()
            )
        elif isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        sizes = value if isinstance(value, tuple) else (value,)
        ok = len(sizes) >= 1 and all(isinstance(v, float) and math.isfinite(v) and v > 0 for v in sizes)
        if not ok:
            raise ValueError(
                "PhysicsConfig.box_half_size must be a finite number > 0 (m) or a tuple of them, one per axis, "
                f"got {self.box_half_size!r}"
            )
        object.__setattr__(self, "box_half_size", value)

    def half_sizes(self, dim: int) -> tuple[float, ...]:
        """The box half-size of each of the ``dim`` axes, in m (the last axis is vertical).

        Raises:
          ValueError: when ``box_half_size`` is a tuple of another length.
        """
        if isinstance(self.box_half_size, tuple):
            if len(self.box_half_size) != dim:
                raise ValueError(
                    f"PhysicsConfig.box_half_size has {len(self.box_half_size)} half-sizes "
                    f"{self.box_half_size} but the particles are in D = {dim}: expected one per axis"
                )
            return self.box_half_size
        return (self.box_half_size,) * dim

    @property
    def height(self) -> float:
        """Half-size of the vertical (last) axis, in m."""
        value = self.box_half_size
        return value[-1] if isinstance(value, tuple) else value

    @property
    def largest_half_size(self) -> float:
        """The largest half-size over all axes, in m."""
        value = self.box_half_size
        return max(value) if isinstance(value, tuple) else value

    @property
    def is_square(self) -> bool:
        """Whether all half-sizes are equal (the paper's square or cubic box)."""
        value = self.box_half_size
        return not isinstance(value, tuple) or len(set(value)) == 1

    def settling_speed(self, radius: float, dim: int = 2) -> float:
        """Terminal speed (m/s) of an isolated particle of ``radius`` m: a disk (D = 2) or a sphere (D = 3).

        Buoyant weight over the drag coefficient ``k a``: ``(rho - rho_f) pi a s g / k`` for a disk,
        ``(rho - rho_f) (4/3) pi a^2 g / k`` for a sphere.
        """
        if dim == 2:
            return (self.density - self.fluid_density) * math.pi * radius * self.thickness * self.gravity / self.drag
        if dim == 3:
            return (self.density - self.fluid_density) * (4.0 / 3.0) * math.pi * radius**2 * self.gravity / self.drag
        raise ValueError(f"spatial dimension must be 2 or 3, got {dim}")

    def to_dict(self) -> dict[str, Any]:
        """The fields as JSON values (a per-axis ``box_half_size`` as a list)."""
        values = dataclasses.asdict(self)
        if isinstance(self.box_half_size, tuple):
            values["box_half_size"] = list(self.box_half_size)
        return values

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> PhysicsConfig:
        """Build a config from a mapping (numbers may be given as text); unknown keys are an error.

        ``box_half_size`` may be a number, a list (JSON) or text such as ``"0.4,0.1"``.
        """
        values = dict(values) if isinstance(values, Mapping) else values
        if isinstance(values, dict) and isinstance(values.get("box_half_size"), str):
            text = values["box_half_size"]
            if "," in text:
                parts = [p.strip() for p in text.strip().strip("()[]").split(",") if p.strip()]
                try:
                    values["box_half_size"] = tuple(float(p) for p in parts)
                except ValueError:
                    raise ValueError(
                        f"PhysicsConfig.box_half_size must be a number or comma-separated numbers, got {text!r}"
                    ) from None
        return config_from_mapping(cls, values)
