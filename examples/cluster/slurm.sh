#!/bin/bash
# A Slurm job array that renders a long sequence in chunks (docs/cli.md, "A long sequence in
# chunks"): task K of N renders the K-th of N contiguous chunks of the frames, warming up on the
# frames before its chunk, with the plan (radius, camera, pool) of the range's first frame, made
# once by whichever task needs it first and read by the others. Rerunning the array renders only
# the frames that are missing (--skip-existing); every PNG is written atomically.
#
#   sbatch --array=1-20 examples/cluster/slurm.sh 'sim/f_{}.vtk' 0..2000 out/
#
#SBATCH --job-name=fluid-surfels
#SBATCH --cpus-per-task=4
#SBATCH --mem=8G
#SBATCH --time=02:00:00
#SBATCH --output=fluid-surfels-%A_%a.log
set -euo pipefail
input=${1:?an input pattern such as 'sim/f_{}.vtk'}
frames=${2:?a frame range such as 0..2000}
out=${3:?an output folder}
mkdir -p "$out"
exec fluid-surfels render --input "$input" --frames "$frames" --out "$out" \
  --shard slurm --plan "$out/plan.json" --skip-existing --threads "${SLURM_CPUS_PER_TASK:-1}"
