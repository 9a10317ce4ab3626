"""jaxfric: a differentiable 2D finite-element simulator of sheet-metal tribology devices, in JAX.

Importing jaxfric enables float64 (``jax_enable_x64``): every computation runs in double precision.
"""

import jax

jax.config.update("jax_enable_x64", True)

from .contact.formulations import (  # noqa: E402
    ALGORITHMS,
    AbstractContactFormulation,
    AugmentedLagrangian,
    Complementarity,
    Penalty,
    formulation,
)
from .contact.friction import FrictionLaw, Polynomial, VelocityDecay  # noqa: E402
from .contact.rigid import Force, Move, RigidTool  # noqa: E402
from .contact.status import OPEN, SLIP, STICK, contact_status  # noqa: E402
from .contact.tools import Tool  # noqa: E402
from .fem.kinematic import KinematicJ2Material  # noqa: E402
from .fem.loading import Affine, DirichletBC, Motion, Phase, Ramp, RigidMotion  # noqa: E402
from .fem.material import J2Material, MaterialState, von_mises  # noqa: E402
from .fem.mesh import StripMesh, graded_coordinates, strip_mesh  # noqa: E402
from .loadpath.controller import StepControl  # noqa: E402
from .loadpath.model import SimState, StripModel, default_observe, initial_state, reactions, stresses  # noqa: E402
from .loadpath.run import Checkpoint, MemoryBudgetError, RunResult, run  # noqa: E402
from .loadpath.simulate import (  # noqa: E402
    LoadPathState,
    Simulation,
    advance,
    begin,
    simulate,
    simulate_fixed,
    simulate_flat,
)
from .loadpath.step import linearize_step, solve_step  # noqa: E402
from .numerics.linalg import BlockTridiag, Bordered, block_tridiag_solve, bordered_solve, dense_solve, linear_solve  # noqa: E402
from .numerics.newton import NewtonOptions  # noqa: E402
from .numerics.results import Result, SimulationError  # noqa: E402

__version__ = "0.1.0"

__all__ = [
    "RigidTool", "Move", "Force", "Tool", "FrictionLaw", "Polynomial", "VelocityDecay",
    "ALGORITHMS", "AbstractContactFormulation", "Penalty", "AugmentedLagrangian", "Complementarity", "formulation",
    "OPEN", "STICK", "SLIP", "contact_status",
    "BlockTridiag", "Bordered", "block_tridiag_solve", "bordered_solve", "dense_solve", "linear_solve",
    "Affine", "DirichletBC", "Motion", "Phase", "Ramp", "RigidMotion",
    "J2Material", "KinematicJ2Material", "MaterialState", "von_mises",
    "StripMesh", "graded_coordinates", "strip_mesh",
    "NewtonOptions", "Result", "SimulationError", "MemoryBudgetError", "RunResult", "Checkpoint", "run",
    "SimState", "Simulation", "StepControl", "StripModel", "default_observe", "initial_state",
    "simulate", "simulate_flat", "simulate_fixed", "begin", "advance", "LoadPathState", "solve_step", "stresses",
    "linearize_step", "reactions",
]
