# Shared by the GPU A/B scripts (sourced): output folder, data path, and run_version, which runs
# `python3 -m warpnerf.cli ARGS` with this tree ("new") or with the base tree in .gpu/base ("base":
# the base commit's warpnerf/ with kernels/ copied to warpnerf/kernels).
set -u
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
DATA=$PWD/${DATA:-.gpu/lego}
run_version() {  # version, argv...
  if [ "$1" = base ]; then shift; (B=$PWD/.gpu/base; cd .gpu/base && PYTHONPATH=${PYTHONPATH:-}:$B python3 -m warpnerf.cli "$@"); else shift; python3 -m warpnerf.cli "$@"; fi
}
