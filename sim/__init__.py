"""Warp CFX engine: models, states and solvers for hair and cloth, the face rig, bodies, garments,
scenes and CLI.

    import sim
    result = sim.run_scene(sim.demo_scene(), "out/demo.usdc")

Lower level: sim.StrandBuilder -> HairModel -> HairSolver.step(state_in, state_out, collider, dt) for
hair; sim.ClothModel.from_garment(sim.fit_dress(body)) -> ClothSolver.step(...) for cloth; colliders
from sim.Collider around sim.procedural_head() or sim.procedural_body(); faces from
sim.FaceRig(sim.builtin_face()) driven by sim.FaceAnimation (expressions, lip sync).
"""

__version__ = "0.1.0"

from .collider import Collider  # noqa: E402
from .detail import ClothDetail, DetailParams, DetailSurface, DetailTopology  # noqa: E402
from .errors import InputError, SimulationError  # noqa: E402
from .face import (ACTION_UNITS, EMOTIONS, FEATURE_POINTS, ExpressionKey, FaceAnimation, FaceConfig,  # noqa: E402
                   FaceMesh, FaceRig, builtin_face, face_from_file)
from .mouth import MOUTH_PARAMETERS, VOWEL_SHAPES, VOWELS  # noqa: E402
from .hair_solver import HairParams, HairSolver  # noqa: E402
from .hairstyle import HairstyleParams, grow_hairstyle, sample_scalp  # noqa: E402
from .head import HeadAnimation, HeadAsset, mesh_head, procedural_head  # noqa: E402
from .body import BodyAnimation, BodyAsset, Skeleton, procedural_body  # noqa: E402
from .cloth import ClothModel, ClothParams, ClothSolver, ClothState  # noqa: E402
from .garment import GARMENTS, GarmentMesh, fit_dress, fit_shirt, fit_skirt, garment_from_file, garment_from_usd  # noqa: E402
from .scene import (BodyConfig, GarmentConfig, HeadConfig, RunResult, Scene, SceneConfig, TimingConfig,  # noqa: E402
                    demo_scene, hair_demo_scene, load_scene, run_scene)
from .sphere_tree import SphereTree, build_sphere_tree  # noqa: E402
from .strands import HairModel, HairState, StrandBuilder  # noqa: E402

__all__ = [
    "ACTION_UNITS", "EMOTIONS", "FEATURE_POINTS", "ExpressionKey", "FaceAnimation", "FaceConfig", "FaceMesh",
    "FaceRig", "builtin_face", "face_from_file", "MOUTH_PARAMETERS", "VOWEL_SHAPES", "VOWELS",
    "BodyAnimation", "BodyAsset", "BodyConfig", "GARMENTS", "GarmentMesh", "Skeleton", "fit_dress", "fit_shirt",
    "fit_skirt", "garment_from_file", "garment_from_usd", "procedural_body", "ClothDetail", "ClothModel", "ClothParams", "ClothSolver", "ClothState", "Collider", "DetailParams",
    "DetailSurface", "DetailTopology", "GarmentConfig",
    "HairModel", "HairParams", "HairSolver", "HairState", "HairstyleParams", "HeadAnimation", "HeadAsset",
    "HeadConfig", "InputError", "RunResult", "Scene", "SceneConfig", "SimulationError", "SphereTree",
    "StrandBuilder", "TimingConfig", "build_sphere_tree", "demo_scene", "grow_hairstyle", "hair_demo_scene",
    "load_scene", "mesh_head", "procedural_head", "run_scene", "sample_scalp",
]
