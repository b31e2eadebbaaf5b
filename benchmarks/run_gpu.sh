#!/usr/bin/env bash
# The GPU benchmark and check session, one part per call (each must end inside 10 minutes):
#   bash benchmarks/run_gpu.sh tests    # graph and statistics checks on cuda and cpu (tests/test_graphs.py, test_quality.py)
#   bash benchmarks/run_gpu.sh hair     # benchmarks/hair.py on cuda with Newton chains (HAIR_ARGS: its
#                                       # options, by default each case with lanes by root and as grown)
#   bash benchmarks/run_gpu.sh fused    # the hair's substep as one launch (HairSolver.fused) against the
#                                       # launches apart, 1k to 100k strands, no peer
#   bash benchmarks/run_gpu.sh cloth    # benchmarks/cloth.py on cuda with Newton VBD and XPBD
#   bash benchmarks/run_gpu.sh cloth-block # the small cloths' steps as one block (ClothSolver.block_step)
#                                       # against their launches: the paper's dress and the walking dress, profiled
#   bash benchmarks/run_gpu.sh pending  # what session 35 left unmeasured, in one call: the hair without a collider
#                                       # (simplified1) and on the sphere tree, each also with the length pass
#                                       # reading ahead, fused, and fused with the frame kept in lanes, profiled;
#                                       # then cloth-block
#   bash benchmarks/run_gpu.sh loose    # the sphere tree's length pass with loose lists (HairSolver.loose_lists:
#                                       # walks only where a leaf may hold a particle), apart and fused in lanes
#   bash benchmarks/run_gpu.sh in-block-tests # the CUDA graph tests of a frame in one launch (HairSolver.frame_in_block),
#                                       # a block of lanes per strand and 32 strands a block (frame_warps)
#   bash benchmarks/run_gpu.sh in-block # both layouts against the device's way at 1k to 100k strands with and
#                                       # without the sphere tree, profiled
#   bash benchmarks/run_gpu.sh in-block-mesh # the same against the mesh (a BVH per substep's pose), simplified and
#                                       # full shape matching (the default model), 1k to 100k strands
#   bash benchmarks/run_gpu.sh in-block-ncu # Nsight Compute on each layout's launch at 100k strands on the sphere tree
#   bash benchmarks/run_gpu.sh frame-layouts # other layouts of the frame (HairSolver.frame_layout, SIDExGROUPSxRUN)
#                                       # at 100k strands on the sphere tree: strands a block against runs a thread
#   bash benchmarks/run_gpu.sh realtime # benchmarks/realtime.py on cuda (the CPU real-time case, for comparison)
#   bash benchmarks/run_gpu.sh ncu      # Nsight Compute's counters (occupancy, warp states, memory) for one
#                                       # launch of the length pass at 1k strands on the mesh and of the fused
#                                       # substep at 100k strands on the sphere tree (as in session 41)
#   bash benchmarks/run_gpu.sh startup  # benchmarks/startup.py on cuda: set-up from the asset cache, and the
#                                       # CUDA modules compiled one after another and side by side (NVRTC)
#   bash benchmarks/run_gpu.sh hair-ab  # benchmarks/hair.py (HAIR_AB_ARGS) run by each earlier tree that
#   bash benchmarks/run_gpu.sh cloth-ab # benchmarks/ab_tree.sh put under .ab/ (carried), then by this one;
#                                       # likewise benchmarks/cloth.py (CLOTH_AB_ARGS)
# Logs go to $OUT (or ./out/gpu); warp-lang, newton, usd-core and trimesh must be importable. Set CFX_COMMIT to
# the commit sent (the device tool's .git is stale), so the logs name it.
set -uo pipefail
out=${OUT:-out/gpu}; mkdir -p "$out"
base=${PYTHONPATH:-}
export PYTHONPATH=.${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1

ab() {  # ab SCRIPT TIMEOUT ARGS...: each tree under .ab/ runs its own copy of SCRIPT, then this tree
  local script=$1 limit=$2; shift 2
  for tree in .ab/*/; do
    [[ -d $tree ]] || continue
    CFX_COMMIT=$(basename "$tree") PYTHONPATH=$tree${base:+:$base} timeout "$limit" python3 "$tree$script" "$@"
  done
  timeout "$limit" python3 "$script" "$@"
}
nvidia-smi --query-gpu=name,memory.total,clocks.max.sm --format=csv,noheader | tee -a "$out/device.txt"
for part in "$@"; do
  case $part in
    tests) timeout 400 python3 -m pytest -q -p no:cacheprovider tests/test_graphs.py tests/test_comb.py tests/test_quality.py 2>&1 | tee "$out/tests.log" ;;
    hair) timeout ${HAIR_TIMEOUT:-540} python3 benchmarks/hair.py --device cuda ${HAIR_ARGS:---lane-order both} 2>&1 |
        tee "$out/hair.log" ;;
    fused) for way in "--fused off" "--fused on" "--fused on --leaves-ahead off"; do
          timeout 180 python3 benchmarks/hair.py --device cuda --no-peer --cases simplified1 simplified1+spheres full+mesh \
              $way 2>&1 | tee -a "$out/fused.log"
        done ;;
    cloth) timeout ${CLOTH_TIMEOUT:-540} python3 benchmarks/cloth.py --device cuda ${CLOTH_ARGS:-} 2>&1 | tee "$out/cloth.log" ;;
    cloth-block) timeout 400 python3 benchmarks/cloth.py --device cuda --peers --grids --detail-sizes 322 322:60 \
        --block both --profile 2>&1 | tee "$out/cloth-block.log" ;;
    pending) timeout 400 python3 benchmarks/hair.py --device cuda --no-peer --strands 1000 100000 \
          --cases simplified1 simplified1+spheres --try read_ahead=on fused=on fused=on,frame_lanes=on --profile 2>&1 |
          tee "$out/pending-hair.log"
        timeout 180 python3 benchmarks/cloth.py --device cuda --peers --grids --detail-sizes 322 322:60 --block both \
          2>&1 | tee "$out/pending-cloth.log" ;;
    loose) timeout 540 python3 benchmarks/hair.py --device cuda --no-peer --strands 1000 100000 \
          --cases simplified1+spheres \
          --try loose_lists=on fused=on,frame_lanes=on fused=on,frame_lanes=on,loose_lists=on \
          --profile 2>&1 | tee "$out/loose-hair.log" ;;
    in-block-tests) timeout 560 python3 -m pytest -q -p no:cacheprovider tests/test_graphs.py -k "in_block or in_warps" 2>&1 |
          tee "$out/in-block-tests.log" ;;
    in-block) timeout 560 python3 benchmarks/hair.py --device cuda --no-peer --strands 1000 10000 100000 \
          --cases simplified1 simplified1+spheres --try frame_in_block=on frame_in_block=on,frame_warps=on --profile \
          2>&1 | tee "$out/in-block-hair.log" ;;
    in-block-mesh) timeout 560 python3 benchmarks/hair.py --device cuda --no-peer --strands 1000 10000 100000 \
          --cases full+mesh simplified+mesh --try frame_in_block=on frame_in_block=on,frame_warps=on --profile 2>&1 |
          tee "$out/in-block-mesh-hair.log" ;;
    in-block-ncu) ncu=$(command -v ncu || ls /opt/nvidia/nsight-compute/*/ncu 2>/dev/null | head -1)
        for way in frame_in_block frame_in_warps; do
          try=frame_in_block=on; [[ $way == frame_in_warps ]] && try=frame_in_block=on,frame_warps=on
          timeout 270 "$ncu" --clock-control none --kernel-name regex:$way --launch-skip 3 --launch-count 1 \
            --section SpeedOfLight --section WarpStateStats --section Occupancy --section LaunchStats \
            --section MemoryWorkloadAnalysis python3 benchmarks/hair.py --device cuda --no-peer --strands 100000 \
            --cases simplified1+spheres --frames 2 --try $try 2>&1 | tee "$out/ncu-100k-$way.txt" | grep -v "^|"
        done ;;
    frame-layouts) layouts=(32x8x4 16x8x4 8x8x4 4x8x4 1x8x4 64x4x8)  # cuda_resources.FRAME_LAYOUTS
        timeout 560 python3 benchmarks/hair.py --device cuda --no-peer --strands 100000 --cases simplified1+spheres \
          --try "${layouts[@]/#/frame_in_block=on,frame_layout=}" 2>&1 | tee "$out/frame-layouts-hair.log" ;;
    realtime) timeout 540 python3 benchmarks/realtime.py --device cuda 2>&1 | tee "$out/realtime.log" ;;
    hair-ab) ab benchmarks/hair.py 250 --device cuda --no-peer ${HAIR_AB_ARGS:---strands 1000 100000 --cases simplified1+spheres full+mesh} 2>&1 |
        tee "$out/hair-ab.log" ;;
    cloth-ab) ab benchmarks/cloth.py 250 --device cuda --peers ${CLOTH_AB_ARGS:---grids --detail-sizes 322} 2>&1 |
        tee "$out/cloth-ab.log" ;;
    ncu) ncu=$(command -v ncu || ls /opt/nvidia/nsight-compute/*/ncu 2>/dev/null | head -1)
        sections="--section SpeedOfLight --section WarpStateStats --section Occupancy --section LaunchStats
          --section MemoryWorkloadAnalysis"
        timeout 150 "$ncu" --clock-control none --kernel-name regex:follow_the_leader_queries --launch-skip 30 \
          --launch-count 1 $sections python3 benchmarks/hair.py --device cuda --no-peer --strands 1000 \
          --cases full+mesh --frames 2 2>&1 | tee "$out/ncu-1k-mesh.txt" | grep -v "^|"
        timeout 200 "$ncu" --clock-control none --kernel-name regex:step_strands_sphere_lists_simplified_loose \
          --launch-skip 30 --launch-count 1 $sections python3 benchmarks/hair.py --device cuda --no-peer \
          --strands 100000 --cases simplified1+spheres --frames 2 2>&1 | tee "$out/ncu-100k-fused.txt" | grep -v "^|" ;;
    startup) timeout 540 python3 benchmarks/startup.py --device cuda --repeats 1 --kernels 2>&1 | tee "$out/startup.log" ;;
    *) echo "unknown part $part"; exit 2 ;;
  esac
done
