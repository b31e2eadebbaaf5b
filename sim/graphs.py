"""Whole frames as graphs, and results read back without waiting.

A frame's launches are captured once and replayed every frame after (FrameGraphs); results are
copied into pinned host memory behind the frame's work (AsyncReadback).

A solver frame is a fixed sequence of launches whose only per-frame inputs live in device arrays
(bone matrices for the substeps, the solver clock, step counters), so one capture serves every
later frame. Python code that ping-pongs state buffers rebinds its references while the frame is
captured; those references are part of the key, and a replay restores what the capture left, so
an odd number of swaps per frame simply alternates between two graphs.

On a CUDA device a frame is one CUDA graph. On the CPU Warp records a frame's operations and
replays them in a loop in C++, without Python's cost per launch; a mesh's BVH refit is the one
operation it does not record there, so a CPU frame is split into recorded pieces with the refits
between them (refit_bvh). Work on disjoint data can be split into branches (run_parallel) that a CPU
frame replays on several threads at once, a refit among them (beside launches that do not read that
BVH), and whole frames of different solvers can be replayed side by side (run_side_by_side). With
graphs disabled `run` calls the frame's function directly, so every path shares one definition of
the frame.
"""

import os
import threading
import warnings
from concurrent.futures import ThreadPoolExecutor

import warp as wp

_cpu_frame = None  # the CPU frame being captured, which refit_bvh and run_parallel split
_pool = None  # worker threads replaying the branches of parallel steps
_sharing = None  # the _SharedCores of the frames running side by side, if any


def _replay_pool():
    """The worker threads that replay branches and side-by-side tasks (started as needed)."""
    global _pool
    if _pool is None:
        _pool = ThreadPoolExecutor(max_workers=16, thread_name_prefix="cfx-replay")
    return _pool


def run_parallel(branches):
    """Run `branches`, functions that only launch work and touch disjoint data (the strand ranges
    of one hair substep), as one step of a frame. In a frame captured on the CPU each branch becomes
    a recorded frame of its own (its mesh refits between its pieces), and a replay runs them on up
    to one thread per core, each thread taking the next branch left: Warp runs a CPU launch on one
    thread, and a replay and a refit release Python's lock, so the branches use the machine's cores,
    and more branches than cores even out their differences. Anywhere else (CUDA, eager frames,
    graphs off) they run one after the other."""
    if len(branches) > 1 and _cpu_frame is not None:
        _cpu_frame.split_parallel(branches)
        return
    for branch in branches:
        branch()


def run_side_by_side(tasks):
    """Run `tasks`, functions that each replay captured frames on data no other task touches (the
    hair and the cloth, each against its own twin of the collider), at the same time on the CPU's
    cores, and return when all are done. A replay releases Python's lock, so a task on a worker
    thread runs beside the first one on this thread; an exception in any task is raised here.

    The tasks share the cores (_SharedCores): each task's thread runs the branches of its own
    parallel steps, spare cores help with them, and a thread whose task is done helps the others
    until all are, so no more threads run than there are cores and none idles while work is left."""
    global _sharing
    if len(tasks) < 2:
        for task in tasks:
            task()
        return
    sharing = _sharing = _SharedCores(len(tasks))

    def run(task):
        try:
            task()
        finally:
            sharing.help_until_done()

    others = [_replay_pool().submit(run, task) for task in tasks[1:]]
    try:
        run(tasks[0])
    finally:
        errors = [other.exception() for other in others]
        _sharing = None
    for error in errors:
        if error is not None:
            raise error


def cpu_cores():
    """Cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


class _SharedCores:
    """The branches of parallel steps of frames that run side by side, claimed one at a time.

    The thread of the frame that reaches a parallel step offers its branches and replays them one
    by one; spare cores (beyond one per frame) claim some from the start, and a thread
    whose own frame is done claims them as it finds them. A step ends when its every branch has.
    """

    def __init__(self, tasks):
        self.ready = threading.Condition()
        self.threads = tasks  # one per frame, busy until all are done (running it, then helping)
        self.running = tasks  # frames not yet done
        self.offers = []  # [branches left, branches not finished, first error] per offered step

    def run_branches(self, graphs):
        offer = [list(graphs), len(graphs), None]
        with self.ready:
            self.offers.append(offer)
            self.ready.notify_all()
        spare = min(len(graphs) - 1, max(0, cpu_cores() - self.threads))
        helpers = [_replay_pool().submit(self._claim_from, offer) for _ in range(spare)]
        self._claim_from(offer)
        with self.ready:
            while offer[1] > 0:
                self.ready.wait()
            self.offers.remove(offer)
        for helper in helpers:
            helper.result()
        if offer[2] is not None:
            raise offer[2]

    def _claim_from(self, offer):
        while True:
            with self.ready:
                if not offer[0]:
                    return
                graph = offer[0].pop(0)
            self._replay(offer, graph)

    def _replay(self, offer, branch):
        try:
            branch.launch()
        except Exception as error:  # raised by the thread that offered the step
            offer[2] = error
        finally:
            with self.ready:
                offer[1] -= 1
                self.ready.notify_all()

    def help_until_done(self):
        with self.ready:
            self.running -= 1
            self.ready.notify_all()
            while self.running > 0:
                offer = next((o for o in self.offers if o[0]), None)
                if offer is None:
                    self.ready.wait()
                    continue
                graph = offer[0].pop(0)
                self.ready.release()
                try:
                    self._replay(offer, graph)
                finally:
                    self.ready.acquire()


def _replay_on_cores(branches):
    """Replay `branches` (the recorded _CpuFrames of one parallel step) on at most one thread per
    core, each thread taking the next branch not yet taken until none is left, and return when all
    are done."""
    run_on_cores([branch.launch for branch in branches])


def run_on_cores(calls):
    """Run `calls` (functions that release Python's lock while they work: graph replays, recorded
    launches) on at most one thread per core, each thread taking the next call not yet taken, and
    return when all are done; the first exception is raised here.

    This thread waits only for the calls helpers have taken, never for a helper to start: waking a
    thread of the pool takes about 50 us on this machine's two cores, and a step whose calls this
    thread finishes first (short ones) need not pay it."""
    left = list(calls)
    state = threading.Condition()
    running = [0, None]  # calls taken by helpers and not finished, the first error

    def claim(helper):
        while True:
            with state:
                if not left:
                    return
                call = left.pop(0)
                running[0] += helper
            try:
                call()
            except BaseException as error:
                if not helper:
                    raise
                running[1] = running[1] or error
            finally:
                if helper:
                    with state:
                        running[0] -= 1
                        state.notify_all()

    for _ in range(min(len(calls), cpu_cores()) - 1):
        _replay_pool().submit(claim, 1)
    try:
        claim(0)
    finally:
        with state:
            left.clear()  # after an error here, helpers take no more
            while running[0] > 0:
                state.wait()
    if running[1] is not None:
        raise running[1]


def core_slices(dim, device, per_core=1):
    """How many slices launch_on_cores cuts `dim` items into: one on a GPU; on the CPU one per core,
    each of at least per_core items."""
    if wp.get_device(device).is_cuda:
        return 1
    return max(1, min(cpu_cores(), dim // max(1, per_core)))


def launch_on_cores(kernel, dim, inputs, device, sliced=(), first=None, part=None, per_core=1):
    """wp.launch(kernel, dim, inputs) with one thread per item, on the CPU in slices of the items side
    by side on the cores (a CPU launch runs on one thread); on a GPU one launch. sliced: the indices
    of the inputs that hold one element per item, sliced with the items; first: the index of an int
    input that takes the slice's first item instead (kernels that read items by their index); part:
    the index of an int input that takes the slice's number (kernels that reduce into a row of their
    own: a CPU's atomics are not atomic across launches); per_core: see core_slices."""
    parts = core_slices(dim, device, per_core)
    cuts = [dim * k // parts for k in range(parts + 1)]

    def arguments(k):
        a, b = cuts[k], cuts[k + 1]
        return [arg[a:b] if i in sliced else (a if i == first else (k if i == part else arg))
                for i, arg in enumerate(inputs)]

    if parts == 1:
        wp.launch(kernel, dim, arguments(0), device=device)
        return
    launches = [wp.launch(kernel, cuts[k + 1] - cuts[k], arguments(k), device=device, record_cmd=True)
                for k in range(parts) if cuts[k + 1] > cuts[k]]
    run_on_cores([launch.launch for launch in launches])


def refit_bvh(structure):
    """structure.refit() (a wp.Mesh or a wp.Bvh), in order also inside a frame being captured on the
    CPU: Warp records a wp.Bvh's refit there but not a wp.Mesh's, so the capture is split around a
    mesh's and its refit runs between the pieces."""
    if isinstance(structure, wp.Mesh) and _cpu_frame is not None and _cpu_frame.device == structure.device:
        _cpu_frame.split(structure.refit)
    else:
        structure.refit()


class _CudaFrame:
    def __init__(self, device):
        self.device, self.graph = device, None

    def capture(self, frame):
        with wp.ScopedCapture(device=self.device) as capture:
            frame()
        self.graph = capture.graph

    def launch(self):
        wp.capture_launch(self.graph)


class _CpuFrame:
    """A frame recorded on the CPU: recorded pieces, and host steps (mesh refits) between them."""

    def __init__(self, device):
        self.device, self.steps = device, []

    def capture(self, frame):
        global _cpu_frame
        outer = _cpu_frame  # a branch of a parallel step is captured inside its frame's capture
        # the frame ran eagerly before, loading what it launches; a CPU capture may load a module too,
        # and loading every module here would compile those of kernels the run never launches
        # (warp_kernels._options.deferred_module)
        wp.capture_begin(device=self.device, force_module_load=False)
        _cpu_frame = self
        try:
            frame()
        except Exception:
            wp.capture_end(device=self.device)
            raise
        finally:
            _cpu_frame = outer
        self.steps.append(wp.capture_end(device=self.device))

    def split(self, host_step):
        self.steps.append(wp.capture_end(device=self.device))
        self.steps.append(host_step)
        wp.capture_begin(device=self.device, force_module_load=False)

    def split_parallel(self, branches):
        """Capture each branch as a frame of its own; launch() replays them at the same time."""
        self.steps.append(wp.capture_end(device=self.device))
        recorded = []
        try:
            for branch in branches:
                recorded.append(_CpuFrame(self.device))
                recorded[-1].capture(branch)
        finally:
            wp.capture_begin(device=self.device, force_module_load=False)  # capture() ends this one
        self.steps.append(tuple(recorded))

    def launch(self):
        kept = []
        for step in self.steps:
            if callable(step):
                step()
                kept.append(step)
                continue
            if isinstance(step, tuple):
                sharing = _sharing
                if sharing is not None:  # beside other frames: they share the cores
                    sharing.run_branches(step)
                else:
                    _replay_on_cores(step)
                kept.append(step)
                continue
            try:
                wp.capture_launch(step)
                kept.append(step)
            except RuntimeError as error:  # a piece with nothing recorded (two refits in a row)
                if "no operations recorded" not in str(error):
                    raise
        self.steps = kept


class FrameGraphs:
    """Per-key captured frames on one device.

    run(key, frame, refs) executes `frame()` (a function that only launches work, refits meshes with
    refit_bvh and rebinds buffer references). The first time a key is seen the frame runs eagerly
    (modules load, caches are built); the second time it is captured and launched; later it is
    replayed. refs = (get, set) reads and restores the Python-side references `frame` rebinds, so a
    replay leaves them as a real run would.
    """

    def __init__(self, device, enabled=True):
        self.device = wp.get_device(device)
        self.enabled = bool(enabled)
        self._graphs = {}
        self._seen = set()
        self._counting = threading.Lock()  # side-by-side tasks replay from two threads
        self.replays = 0  # frames launched from a graph (reported by benchmarks and tests)

    def run(self, key, frame, refs=None):
        get, put = refs if refs is not None else (lambda: None, lambda value: None)
        if not self.enabled:
            frame()
            return
        entry = self._graphs.get(key)
        if entry is not None:
            graph, after = entry
            graph.launch()
            put(after)
            with self._counting:
                self.replays += 1
            return
        if key not in self._seen:
            self._seen.add(key)
            frame()
            return
        before = get()
        graph = _CudaFrame(self.device) if self.device.is_cuda else _CpuFrame(self.device)
        try:
            graph.capture(frame)
        except Exception as error:  # an operation that cannot be captured: keep running, uncaptured
            put(before)
            self.enabled = False
            warnings.warn(f"graph capture failed, stepping without graphs: {error}", RuntimeWarning, stacklevel=2)
            frame()
            return
        self._graphs[key] = (graph, get())
        graph.launch()  # a capture only records: this runs the frame
        self.replays += 1

    def captured(self, key):
        """Whether run(key, ...) would replay a captured frame: only replays may run side by side
        (captures on one device are serial)."""
        return self.enabled and key in self._graphs

    def forget(self, name):
        """Forget one solver's captured frames (keys starting with `name`), after its model or
        buffers were replaced (a haircut); the other solvers keep theirs."""
        def mine(key):
            while isinstance(key, tuple) and key:  # keys may nest: (("hair", comb), animate, buffer)
                key = key[0]
            return key == name

        self._graphs = {k: g for k, g in self._graphs.items() if not mine(k)}
        self._seen = {k for k in self._seen if not mine(k)}

    def clear(self):
        """Forget captured frames (after a solver's constants or buffers changed, e.g. a reset)."""
        self._graphs.clear()
        self._seen.clear()


class AsyncReadback:
    """Device arrays copied into pinned host memory without waiting, so the host writes one frame
    while the device computes the next.

    begin({name: wp.array}) queues the copies behind the work already launched and returns a
    function that waits for them and gives {name: NumPy array}. Buffers rotate over `slots`, so a
    result must be consumed before `slots` more begin() calls. On the CPU the copies are immediate.
    """

    def __init__(self, device, slots=2):
        self.device = wp.get_device(device)
        self.slots = slots
        self._buffers = [{} for _ in range(slots)]
        self._events = [None] * slots
        self._next = 0

    def begin(self, arrays):
        if not self.device.is_cuda:
            ready = {name: a.numpy().copy() for name, a in arrays.items()}
            return lambda: ready
        slot = self._next
        buffers = self._buffers[slot]
        self._next = (self._next + 1) % self.slots
        for name, a in arrays.items():
            host = buffers.get(name)
            if host is None or host.shape != a.shape or host.dtype != a.dtype:
                host = buffers[name] = wp.empty(a.shape, dtype=a.dtype, device="cpu", pinned=True)
            wp.copy(host, a)
        event = self._events[slot]
        if event is None:
            event = self._events[slot] = wp.Event(self.device)
        wp.record_event(event)

        def wait():
            wp.synchronize_event(event)
            return {name: buffers[name].numpy() for name in arrays}

        return wait
