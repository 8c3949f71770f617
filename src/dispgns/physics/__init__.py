"""Ground-truth physics: truncated-LJ disks with drag, gravity and lossy walls (SI units)."""

from dispgns.physics.config import PhysicsConfig
from dispgns.physics.forces import external_force, interaction_force, particle_mass, particle_volume
from dispgns.physics.initial import (
    InitialState,
    PlacementError,
    particle_count_range,
    place_particles,
    sample_initial_state,
)
from dispgns.physics.integrate import (
    PhysicsCapacity,
    SimState,
    SimulatedFrames,
    euler_integrator,
    neighbor_fn_for,
    simulate,
    simulate_batch,
    simulate_scan,
    update_neighbors,
)
from dispgns.physics.walls import WallResult, resolve_walls

__all__ = [
    "PhysicsConfig",
    "SimState",
    "SimulatedFrames",
    "PhysicsCapacity",
    "InitialState",
    "PlacementError",
    "WallResult",
    "euler_integrator",
    "simulate",
    "simulate_batch",
    "simulate_scan",
    "sample_initial_state",
    "place_particles",
    "particle_count_range",
    "neighbor_fn_for",
    "update_neighbors",
    "interaction_force",
    "external_force",
    "particle_mass",
    "particle_volume",
    "resolve_walls",
]
