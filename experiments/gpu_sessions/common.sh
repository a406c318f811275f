# The part every GPU session driver here shares (sourced by 2026-12-02.sh and 2026-12-02b.sh,
# with the phase as $1): paths, the result archive, the deadline, pinning, step and ttq.
set -u
R=$(pwd)
ln -sfn "$R/kernels" "$R/warpnerf/kernels"
export PYTHONPATH=/tmp/site:$R PYTHONUNBUFFERED=1
FINAL=${OUT:-/tmp/out}; OUT=/root/res/$1; rm -rf "$OUT"; mkdir -p "$OUT" "$FINAL"
trap 'tar czf $FINAL/$1.tgz -C /root/res $1 2>/dev/null' EXIT
S=/root/stage; Q=/root/q; mkdir -p $S $Q
DEADLINE=$(( $(date +%s) + ${LIMIT:-560} ))
left() { echo $(( DEADLINE - $(date +%s) - ${1:-0} )); }
pin() { OMP_NUM_THREADS=8 MKL_NUM_THREADS=8 taskset -c 0-15 "$@"; }
step() {  # name seconds-wanted command...: runs it under the deadline, logs to $OUT/name.log
  local name=$1 want=$2; shift 2
  local l; l=$(left 5)
  if [ "$l" -lt "$want" ]; then echo "$name skipped (left $l s < $want s)" >> $OUT/fail.txt; return; fi
  local t0; t0=$(date +%s)
  pin timeout "$l" "$@" > "$OUT/$name.log" 2>&1 || echo "$name failed rc=$?" >> $OUT/fail.txt
  echo "$name wall $(( $(date +%s) - t0 )) s" >> $OUT/walls.txt
}
ttq() {  # name want ttq-args...: scripts/time_to_quality.py run into $Q/name, its JSON kept
  local name=$1 want=$2; shift 2
  rm -rf "${Q:?}/$name"; mkdir -p "$Q/$name"
  step "$name" "$want" python3 scripts/time_to_quality.py run "$Q/$name" "$@"
  cp "$Q/$name/ttq.json" "$OUT/$name.ttq.json" 2>/dev/null
}
cuda_setup() {  # test files...: the import, the data, the CUDA variants of those tests (a
  # driver's setup phase since 2026-12-05.sh)
  python3 -c "import warpnerf, warp, torch; print('ok', torch.__version__, warp.__version__, torch.cuda.get_device_name(0))"
  cat "$R/.commit" 2>/dev/null; cp -r .gpu/data/* $S/ 2>/dev/null
  local l; l=$(left 5)
  timeout "$l" python3 -m pytest -o addopts=-ra -q -k cuda -p no:cacheprovider "$@" \
    > $OUT/cuda_tests.log 2>&1
  echo "pytest rc=$?" >> $OUT/cuda_tests.log; tail -8 $OUT/cuda_tests.log
}
tail_out() {  # a phase's summary: the walls, the result tables' rows (each with its log's name),
  # what failed or was skipped
  cat $OUT/walls.txt; grep "^|" $OUT/*.log; cat $OUT/fail.txt 2>/dev/null; true
}
