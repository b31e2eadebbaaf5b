"""Drive the hair solver from Python: build a head, groom it, step it, write a cache.

    python examples/python_api.py out/api.usdc
"""

import sys

import numpy as np

import sim
from io_usd import CacheWriter

out = sys.argv[1] if len(sys.argv) > 1 else "out/api.usdc"
device = "cpu"

head = sim.procedural_head()
collider = sim.Collider("head", head.vertices, head.faces, head.skin_indices, head.skin_weights,
                        head.num_bones, device)
animation = sim.HeadAnimation(turn_degrees=30.0, nod_degrees=0.0)
collider.set_poses(animation.bone_matrices([0.0]))
collider.apply_pose(0)

roots, _, _, normals = sim.sample_scalp(head.vertices, head.faces, head.scalp_faces, count=800, seed=3)
points, counts, widths = sim.grow_hairstyle(sim.HairstyleParams(style="curly", vertices=24), roots, normals,
                                            collider.push_out)
model = sim.StrandBuilder().add_strands(points, counts, widths).finalize(device).bind_to_mesh(
    collider.posed_points(), head.faces)
params = sim.HairParams(substeps=8, wind=(1.0, 0.0, 0.0))
solver = sim.HairSolver(model, params)
state, scratch = model.state(), model.state()

fps, frames = 24.0, 24
dt = 1.0 / (fps * params.substeps)
with CacheWriter(out, fps, 1, frames, settings={"solver": params.as_dict()}) as cache:
    cache.add_mesh("head", "collider", head.vertices, head.faces)
    cache.add_curves("hair", "hair", counts, widths)
    t = 0.0
    for frame in range(1, frames + 1):
        if frame > 1:
            times = t + dt * np.arange(1, params.substeps + 1)
            collider.set_poses(animation.bone_matrices(times))
            for k in range(params.substeps):
                collider.apply_pose(k)
                solver.step(state, scratch, collider, dt, float(times[k]))
                state, scratch = scratch, state
            t = float(times[-1])
        solver.check_health(state, frame, "/World/hair")
        cache.write_frame(frame, {"head": collider.posed_points(), "hair": state.x.numpy()})
print(f"wrote {out}")
