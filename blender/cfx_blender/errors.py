"""The add-on's user-facing errors, and the engine import that can fail with one of them."""


class UserError(ValueError):
    """A one-line reason naming the object (or setting) at fault, reported by the operator."""


def engine():
    """The engine's (Simulation, CacheWriter), or UserError saying how to install it."""
    try:
        from io_usd.cache import CacheWriter
        from sim.embed import Simulation
    except ImportError as err:
        raise UserError(f"the Warp CFX engine is not installed in Blender's Python ({err}); "
                        "pip install the repository into it (see blender/README.md)") from None
    return Simulation, CacheWriter


def engine_errors():
    """The exception types the engine raises for bad input or a failed simulation (none without it)."""
    try:
        from sim.errors import InputError, SimulationError
    except ImportError:
        return ()
    return InputError, SimulationError
