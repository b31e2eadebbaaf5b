"""Warp CFX engine: models, states and solvers for hair (and later cloth and faces), scenes and CLI.

    import sim
    result = sim.run_scene(sim.demo_scene(), "out/demo.usdc")

Lower level: sim.StrandBuilder -> HairModel, HairModel.state(), HairSolver.step(state_in, state_out,
collider, dt), with colliders from sim.Collider and heads from sim.procedural_head.
"""

__version__ = "0.1.0"

from .collider import Collider  # noqa: E402
from .errors import InputError, SimulationError  # noqa: E402
from .hair_solver import HairParams, HairSolver  # noqa: E402
from .hairstyle import HairstyleParams, grow_hairstyle, sample_scalp  # noqa: E402
from .head import HeadAnimation, HeadAsset, mesh_head, procedural_head  # noqa: E402
from .cloth import ClothModel, ClothParams, ClothSolver, ClothState  # noqa: E402
from .scene import (BodyConfig, GarmentConfig, HeadConfig, RunResult, Scene, SceneConfig, TimingConfig,  # noqa: E402
                    demo_scene, hair_demo_scene, load_scene, run_scene)
from .sphere_tree import SphereTree, build_sphere_tree  # noqa: E402
from .strands import HairModel, HairState, StrandBuilder  # noqa: E402

__all__ = [
    "BodyConfig", "ClothModel", "ClothParams", "ClothSolver", "ClothState", "Collider", "GarmentConfig",
    "HairModel", "HairParams", "HairSolver", "HairState", "HairstyleParams", "HeadAnimation", "HeadAsset",
    "HeadConfig", "InputError", "RunResult", "Scene", "SceneConfig", "SimulationError", "SphereTree",
    "StrandBuilder", "TimingConfig", "build_sphere_tree", "demo_scene", "grow_hairstyle", "hair_demo_scene",
    "load_scene", "mesh_head", "procedural_head", "run_scene", "sample_scalp",
]
