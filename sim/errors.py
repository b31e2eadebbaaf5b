"""Errors a user can act on: each names the file (or prim), the key and the reason in one line."""


class InputError(ValueError):
    """Bad user input: a scene file, mesh, array or option. The CLI exits with status 2."""

    def __init__(self, source, key, reason):
        self.source, self.key, self.reason = str(source), key, reason
        where = f"{self.source}: {key}: " if key else f"{self.source}: "
        super().__init__(where + reason)


class SimulationError(RuntimeError):
    """The simulation became non-finite or exploded; names the frame and the prim."""

    def __init__(self, frame, prim, reason):
        self.frame, self.prim, self.reason = frame, prim, reason
        super().__init__(f"frame {frame}: {prim}: {reason}")
