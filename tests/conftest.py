import atexit
import os
import shutil
import tempfile

import numpy as np
import pytest
import warp as wp

import warp_kernels

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
# a fresh asset cache for each test session (the commands the tests start inherit it): every builder
# runs at least once per session, whatever the user's own cache holds
os.environ["CFX_CACHE_DIR"] = tempfile.mkdtemp(prefix="cfx-test-assets-")
atexit.register(shutil.rmtree, os.environ["CFX_CACHE_DIR"], True)
from sim.scene import quiet_warp  # noqa: E402

quiet_warp()
wp.init()
# a cold kernel cache (CI) compiles side by side once, not module by module in tests; with the modules of
# kernels only some runs launch (the GPU's ways, which the tests run on the CPU too)
warp_kernels.load("cpu", deferred=True)


@pytest.fixture(scope="session")
def head():
    from sim.head import procedural_head

    return procedural_head()


@pytest.fixture(scope="session")
def head_collider(head):
    from sim.collider import Collider
    from sim.head import HeadAnimation

    c = Collider("head", head.vertices, head.faces, head.skin_indices, head.skin_weights, head.num_bones, "cpu")
    c.set_poses(HeadAnimation.preset("none").bone_matrices([0.0]))
    c.apply_pose(0)
    return c


def helix(n, radius, pitch, turns, axis_down=True):
    """A helix hanging along -Y from the origin, sampled with n points."""
    t = np.linspace(0.0, 2.0 * np.pi * turns, n)
    pts = np.stack([radius * np.cos(t) - radius, -pitch * t / (2.0 * np.pi), radius * np.sin(t)], 1)
    return pts if axis_down else pts[:, [1, 0, 2]]
