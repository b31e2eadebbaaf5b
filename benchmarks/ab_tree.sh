#!/usr/bin/env bash
# An earlier commit's engine and benchmarks beside the working tree, for an A/B in one GPU call:
#   bash benchmarks/ab_tree.sh COMMIT [COMMIT...]   # here: writes .ab/SHORT/ (git-ignored), ~2 MB each
# then carry ".ab" in the device call and run `bash benchmarks/run_gpu.sh hair-ab` (or cloth-ab): each
# tree under .ab/ and then the working tree run the same benchmark in the same call, each log line
# naming its commit. Drop the trees with `rm -rf .ab`.
set -euo pipefail
cd "$(git rev-parse --show-toplevel)"
grep -qxF '/.ab/' .git/info/exclude 2>/dev/null || echo '/.ab/' >> .git/info/exclude
for rev in "$@"; do
  short=$(git rev-parse --short "$rev")
  rm -rf ".ab/$short"; mkdir -p ".ab/$short"
  git archive "$short" sim warp_kernels benchmarks io_usd examples | tar -x -C ".ab/$short"
  echo ".ab/$short: $(git log -1 --format='%h %s' "$short" | cut -c1-100)"
done
