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

# each public name and the submodule that defines it: a submodule loads when one of its names is first
# used, so `cfx --help` and `cfx info` do not load Warp, SciPy and trimesh (about 1.5 s)
_SOURCES = {
    "collider": ["Collider"],
    "detail": ["ClothDetail", "DetailParams", "DetailSurface", "DetailTopology"],
    "errors": ["InputError", "SimulationError"],
    "face": ["ACTION_UNITS", "EMOTIONS", "FEATURE_POINTS", "ExpressionKey", "FaceAnimation", "FaceConfig", "FaceMesh",
             "FaceRig", "builtin_face", "face_from_file"],
    "mouth": ["MOUTH_PARAMETERS", "VOWEL_SHAPES", "VOWELS"],
    "hair_solver": ["HairParams", "HairSolver"],
    "hairstyle": ["HairstyleParams", "grow_hairstyle", "sample_scalp"],
    "head": ["HeadAnimation", "HeadAsset", "mesh_head", "procedural_head"],
    "body": ["BodyAnimation", "BodyAsset", "Skeleton", "procedural_body"],
    "cloth": ["ClothModel", "ClothParams", "ClothSolver", "ClothState"],
    "garment": ["GARMENTS", "GarmentMesh", "fit_dress", "fit_shirt", "fit_skirt", "garment_from_file",
                "garment_from_usd"],
    "scene": ["BodyConfig", "GarmentConfig", "HeadConfig", "RunResult", "Scene", "SceneConfig", "TimingConfig",
              "demo_scene", "hair_demo_scene", "load_scene", "run_scene"],
    "sphere_tree": ["SphereTree", "build_sphere_tree"],
    "strands": ["HairModel", "HairState", "StrandBuilder"],
}
_SOURCE_OF = {name: module for module, names in _SOURCES.items() for name in names}
__all__ = sorted(_SOURCE_OF)


def __getattr__(name):
    module = _SOURCE_OF.get(name)
    if module is None:
        raise AttributeError(f"module 'sim' has no attribute {name!r}")
    from importlib import import_module

    value = getattr(import_module(f".{module}", __name__), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
