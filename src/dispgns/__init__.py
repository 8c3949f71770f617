"""dispgns: learned simulation of finite-size particle suspensions with graph networks."""

__version__ = "0.1.0"

from dispgns.physics import (
    PhysicsConfig,
    SimState,
    euler_integrator,
    sample_initial_state,
    simulate,
    simulate_batch,
)

__all__ = [
    "__version__",
    "PhysicsConfig",
    "SimState",
    "euler_integrator",
    "sample_initial_state",
    "simulate",
    "simulate_batch",
]
