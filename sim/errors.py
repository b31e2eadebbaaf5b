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


class Stopped(KeyboardInterrupt):
    """SIGTERM or SIGHUP (a farm's cancel, a closed terminal) raised in the main thread, so a run
    stops the way Ctrl-C stops it: the partial output discarded, an existing one left as it was."""

    def __init__(self, signum):
        super().__init__(signum)
        self.signum = signum


# signals received during a run, recorded besides the exception their handler raises: that exception
# can land where it is swallowed (a Warp object's __del__ run by the collector, a lock's release in a
# pool) and the run then went on to write its output and exit 0
_stops = []


def record_stop(signum):
    _stops.append(signum)


def clear_stops():
    _stops.clear()


def stop_requested():
    """The first signal recorded since clear_stops(), or None."""
    return _stops[0] if _stops else None


def raise_if_stopped():
    """Raise the recorded stop again (KeyboardInterrupt for SIGINT, Stopped for the others): called at
    each frame and before an output is committed, so a stop that was swallowed still stops the run."""
    import signal

    signum = stop_requested()
    if signum is None:
        return
    if signum == signal.SIGINT:
        raise KeyboardInterrupt
    raise Stopped(signum)
